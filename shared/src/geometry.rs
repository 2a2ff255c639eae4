//! Geometry in the world frame (ENU metres, z up).

pub use nalgebra::{Matrix3, Vector3};

/// A point or vector in the world frame, metres (or m/s).
pub type Vec3 = Vector3<f64>;

/// Horizontal (x, y) distance between two points.
pub fn horizontal_distance(a: &Vec3, b: &Vec3) -> f64 {
    ((a.x - b.x).powi(2) + (a.y - b.y).powi(2)).sqrt()
}

/// True when every component is finite (no NaN or infinity from a model or a wire).
pub fn is_finite(v: &Vec3) -> bool {
    v.iter().all(|c| c.is_finite())
}
