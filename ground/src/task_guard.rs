//! Tasks that end with their owner.

/// Aborts a spawned task when dropped, so the task ends with the scope or future that holds
/// the guard, however that ends.
pub struct AbortOnDrop<T>(pub tokio::task::JoinHandle<T>);

impl<T> Drop for AbortOnDrop<T> {
    fn drop(&mut self) {
        self.0.abort();
    }
}
