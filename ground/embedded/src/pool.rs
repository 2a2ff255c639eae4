//! What the products and attentions share to run on candle's thread pool.

/// A buffer's pointer shared by the pool's tasks, each writing its own elements.
pub struct Shared<T>(pub *mut T);

impl<T> Clone for Shared<T> {
    fn clone(&self) -> Self {
        *self
    }
}
impl<T> Copy for Shared<T> {}

// SAFETY: the tasks write disjoint elements (see the callers), and the pool's call returns
// only when every task is done.
unsafe impl<T> Send for Shared<T> {}
unsafe impl<T> Sync for Shared<T> {}

impl<T> Shared<T> {
    pub fn at(self, offset: usize) -> *mut T {
        self.0.wrapping_add(offset)
    }

    /// The `len` elements from `at`, for one task to fill.
    ///
    /// # Safety
    /// `at..at + len` is inside the buffer, and no other task reads or writes it while the
    /// slice lives.
    #[allow(clippy::mut_from_ref)]
    pub unsafe fn part(&self, at: usize, len: usize) -> &mut [T] {
        unsafe { std::slice::from_raw_parts_mut(self.0.add(at), len) }
    }
}

impl<T: Copy> Shared<T> {
    /// # Safety
    /// `at..at + row.len()` is inside the buffer and no other task writes it.
    pub unsafe fn write(self, at: usize, row: &[T]) {
        unsafe { std::ptr::copy_nonoverlapping(row.as_ptr(), self.0.add(at), row.len()) };
    }
}
