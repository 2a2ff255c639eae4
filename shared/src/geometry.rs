//! Geometry in the world frame (ENU metres, z up).

pub use nalgebra::{Matrix3, Vector3};

/// A point or vector in the world frame, metres (or m/s).
pub type Vec3 = Vector3<f64>;

/// Horizontal (x, y) distance between two points.
pub fn horizontal_distance(a: &Vec3, b: &Vec3) -> f64 {
    ((a.x - b.x).powi(2) + (a.y - b.y).powi(2)).sqrt()
}

/// True when every component is finite (no NaN or infinity from a model or a wire).
///
/// Written out rather than through nalgebra's iterator: the planner checks every point of
/// every neighbour's path before each solve, and the iterator, instantiated in this crate at
/// its opt-level 1, took 1.2 % of both cores in the 20-drone swap (`perf`, issue 19 item 3).
#[inline]
pub fn is_finite(v: &Vec3) -> bool {
    v.x.is_finite() && v.y.is_finite() && v.z.is_finite()
}
