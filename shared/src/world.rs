//! The world: bounds, ellipsoid obstacles, named landmarks.

use crate::geometry::{Matrix3, Vec3, horizontal_distance, is_finite};
use serde::{Deserialize, Serialize};
use std::fmt;

/// An axis-aligned box the drones must stay inside (world ENU).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Bounds {
    pub min: Vec3,
    pub max: Vec3,
}

impl Bounds {
    pub fn contains(&self, p: &Vec3) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] && p[i] <= self.max[i])
    }

    /// Inside with at least `margin` to every face.
    pub fn contains_with_margin(&self, p: &Vec3, margin: f64) -> bool {
        (0..3).all(|i| p[i] >= self.min[i] + margin && p[i] <= self.max[i] - margin)
    }
}

/// `{x : (x-c)ᵀ A (x-c) ≤ 1}` with A symmetric positive definite.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ellipsoid {
    pub name: String,
    pub center: Vec3,
    pub shape: Matrix3<f64>,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum EllipsoidError {
    #[error("ellipsoid {0}: the matrix is not symmetric")]
    NotSymmetric(String),
    #[error("ellipsoid {0}: the matrix is not positive definite")]
    NotPositiveDefinite(String),
    #[error("ellipsoid {0}: semi-axes must be finite and positive")]
    BadSemiAxes(String),
}

impl Ellipsoid {
    /// Validates that `shape` is symmetric positive definite.
    pub fn new(
        name: impl Into<String>,
        center: Vec3,
        shape: Matrix3<f64>,
    ) -> Result<Self, EllipsoidError> {
        let name = name.into();
        if !shape.iter().all(|v| v.is_finite()) || !is_finite(&center) {
            return Err(EllipsoidError::NotPositiveDefinite(name));
        }
        if (shape - shape.transpose()).abs().max() > 1e-9 * shape.abs().max().max(1.0) {
            return Err(EllipsoidError::NotSymmetric(name));
        }
        if shape.cholesky().is_none() {
            return Err(EllipsoidError::NotPositiveDefinite(name));
        }
        Ok(Ellipsoid {
            name,
            center,
            shape,
        })
    }

    /// An ellipsoid with semi-axes `axes` along x, y, z, rotated by `yaw` (radians) about z.
    pub fn from_semi_axes(
        name: impl Into<String>,
        center: Vec3,
        axes: Vec3,
        yaw: f64,
    ) -> Result<Self, EllipsoidError> {
        let name = name.into();
        if !axes.iter().all(|a| a.is_finite() && *a > 0.0) {
            return Err(EllipsoidError::BadSemiAxes(name));
        }
        let rot = nalgebra::Rotation3::from_axis_angle(&Vec3::z_axis(), yaw);
        let diag = Matrix3::from_diagonal(&Vec3::new(
            1.0 / axes.x.powi(2),
            1.0 / axes.y.powi(2),
            1.0 / axes.z.powi(2),
        ));
        let shape = rot.matrix() * diag * rot.matrix().transpose();
        Ellipsoid::new(name, center, (shape + shape.transpose()) * 0.5)
    }

    /// `(p-c)ᵀ A (p-c)`: ≤ 1 inside.
    pub fn level(&self, p: &Vec3) -> f64 {
        let d = p - self.center;
        d.dot(&(self.shape * d))
    }

    pub fn contains(&self, p: &Vec3) -> bool {
        self.level(p) <= 1.0
    }

    /// Semi-axis lengths and their directions (columns), from the eigen-decomposition of A.
    pub fn principal_axes(&self) -> (Vec3, Matrix3<f64>) {
        let eig = self.shape.symmetric_eigen();
        let axes = eig
            .eigenvalues
            .map(|l| 1.0 / l.max(f64::MIN_POSITIVE).sqrt());
        (axes, eig.eigenvectors)
    }

    /// An ellipsoid that contains every point within `margin` of this one (semi-axes grown by
    /// `margin`; this contains the Minkowski sum with a ball of that radius).
    pub fn inflated(&self, margin: f64) -> Ellipsoid {
        let (axes, dirs) = self.principal_axes();
        let grown = axes.map(|a| a + margin.max(0.0));
        let diag = Matrix3::from_diagonal(&grown.map(|a| 1.0 / (a * a)));
        let shape = dirs * diag * dirs.transpose();
        Ellipsoid {
            name: self.name.clone(),
            center: self.center,
            shape: (shape + shape.transpose()) * 0.5,
        }
    }

    /// True when the segment from `a` to `b` enters the ellipsoid.
    pub fn segment_intersects(&self, a: &Vec3, b: &Vec3) -> bool {
        // level(t) = (d + t u)ᵀ A (d + t u) is a convex quadratic in t; minimise over [0, 1].
        let d = a - self.center;
        let u = b - a;
        let au = self.shape * u;
        let quad = u.dot(&au);
        let t = if quad > 0.0 {
            (-d.dot(&au) / quad).clamp(0.0, 1.0)
        } else {
            0.0
        };
        self.contains(&(a + u * t))
    }

    /// A lower bound on the Euclidean distance from `p` to the ellipsoid's surface when `p` is
    /// outside (0 inside): the level-set distance scaled by the smallest semi-axis.
    pub fn clearance_lower_bound(&self, p: &Vec3) -> f64 {
        let level = self.level(p);
        if level <= 1.0 {
            return 0.0;
        }
        let (axes, _) = self.principal_axes();
        (level.sqrt() - 1.0) * axes.min()
    }
}

#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LandmarkKind {
    Car,
    Villa,
    Tree,
    Skyscraper,
    Pad,
    Park,
    District,
    Building,
}

impl LandmarkKind {
    pub fn as_str(self) -> &'static str {
        match self {
            LandmarkKind::Car => "car",
            LandmarkKind::Villa => "villa",
            LandmarkKind::Tree => "tree",
            LandmarkKind::Skyscraper => "skyscraper",
            LandmarkKind::Pad => "pad",
            LandmarkKind::Park => "park",
            LandmarkKind::District => "district",
            LandmarkKind::Building => "building",
        }
    }
}

impl fmt::Display for LandmarkKind {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(self.as_str())
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Landmark {
    pub name: String,
    pub kind: LandmarkKind,
    pub position: Vec3,
}

/// Why a point is not a place a drone may be sent.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum PointRejection {
    #[error("({x:.1}, {y:.1}, {z:.1}) is not a finite point", x = .0.x, y = .0.y, z = .0.z)]
    NotFinite(Vec3),
    /// The point, and the flight area (said, so the pilot or model knows what would do).
    #[error(
        "({x:.1}, {y:.1}, {z:.1}) is outside the flight area (x {x0:.0} to {x1:.0}, y {y0:.0} to {y1:.0}, altitude {z0:.0} to {z1:.0} m)",
        x = .0.x, y = .0.y, z = .0.z,
        x0 = .1.min.x, x1 = .1.max.x, y0 = .1.min.y, y1 = .1.max.y, z0 = .1.min.z, z1 = .1.max.z
    )]
    OutOfBounds(Vec3, Bounds),
    /// The point, the obstacle, and the nearest point clear of every obstacle straight away
    /// from its centre at the same altitude, when there is one in the flight area.
    #[error(
        "({x:.1}, {y:.1}, {z:.1}) is inside obstacle {1} (with the drone's safety margin){clear}",
        x = .0.x, y = .0.y, z = .0.z, clear = clear_of_it(.2)
    )]
    InsideObstacle(Vec3, String, Option<Vec3>),
}

/// The suggestion of [`PointRejection::InsideObstacle`], as it is read.
fn clear_of_it(point: &Option<Vec3>) -> String {
    match point {
        Some(p) => format!(
            "; clear of it at that altitude: ({:.1}, {:.1}, {:.1})",
            p.x, p.y, p.z
        ),
        None => String::new(),
    }
}

#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct World {
    pub bounds: Bounds,
    pub obstacles: Vec<Ellipsoid>,
    pub landmarks: Vec<Landmark>,
}

impl World {
    pub fn landmark(&self, name: &str) -> Option<&Landmark> {
        self.landmarks.iter().find(|l| l.name == name)
    }

    /// Checks that a drone of radius `radius` may be at `p`: finite, inside the bounds, outside
    /// every obstacle inflated by `radius`.
    pub fn check_point(&self, p: &Vec3, radius: f64) -> Result<(), PointRejection> {
        if !is_finite(p) {
            return Err(PointRejection::NotFinite(*p));
        }
        if !self.bounds.contains(p) {
            return Err(PointRejection::OutOfBounds(*p, self.bounds));
        }
        match self.obstacle_at(p, radius) {
            Some(o) => Err(PointRejection::InsideObstacle(
                *p,
                o.name.clone(),
                self.clear_point_from(o, p, radius),
            )),
            None => Ok(()),
        }
    }

    fn obstacle_at(&self, p: &Vec3, radius: f64) -> Option<&Ellipsoid> {
        self.obstacles
            .iter()
            .find(|o| o.inflated(radius).contains(p))
    }

    /// The first point, in 1 m steps from `p` straight away from `obstacle`'s centre at `p`'s
    /// altitude (east when `p` is above the centre), that a drone of `radius` may be at; `None`
    /// when the flight area ends first.
    fn clear_point_from(&self, obstacle: &Ellipsoid, p: &Vec3, radius: f64) -> Option<Vec3> {
        let away = Vec3::new(p.x - obstacle.center.x, p.y - obstacle.center.y, 0.0);
        let away = if away.norm() > 1e-6 {
            away.normalize()
        } else {
            Vec3::new(1.0, 0.0, 0.0)
        };
        (1..)
            .map(|step| p + away * f64::from(step))
            .take_while(|q| self.bounds.contains(q))
            .find(|q| self.obstacle_at(q, radius).is_none())
    }

    /// The first obstacle (inflated by `radius`) that the straight segment a→b crosses.
    pub fn segment_blocked_by(&self, a: &Vec3, b: &Vec3, radius: f64) -> Option<&Ellipsoid> {
        self.obstacles
            .iter()
            .find(|o| o.inflated(radius).segment_intersects(a, b))
    }

    /// The landmark closest (horizontally) to `p` within `radius`, if any.
    pub fn nearest_landmark(&self, p: &Vec3, radius: f64) -> Option<&Landmark> {
        self.landmarks
            .iter()
            .map(|l| (horizontal_distance(&l.position, p), l))
            .filter(|(d, _)| *d <= radius)
            .min_by(|a, b| a.0.total_cmp(&b.0))
            .map(|(_, l)| l)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tower() -> Ellipsoid {
        Ellipsoid::from_semi_axes(
            "tower",
            Vec3::new(0.0, 0.0, 0.0),
            Vec3::new(10.0, 10.0, 90.0),
            0.0,
        )
        .expect("valid")
    }

    /// A refused point says what would do: the flight area, or a point clear of the obstacle.
    #[test]
    fn a_refused_point_says_what_would_do() {
        let world = World {
            bounds: Bounds {
                min: Vec3::new(-100.0, -100.0, 0.0),
                max: Vec3::new(100.0, 100.0, 60.0),
            },
            obstacles: vec![tower()],
            landmarks: Vec::new(),
        };
        let outside = world.check_point(&Vec3::new(150.0, 0.0, 10.0), 0.5);
        assert_eq!(
            outside.map_err(|e| e.to_string()),
            Err("(150.0, 0.0, 10.0) is outside the flight area (x -100 to 100, y -100 to 100, altitude 0 to 60 m)".into())
        );
        // Inside the tower (radius 10, 0.5 m margin), west of its centre: clear 11 m west.
        let inside = world.check_point(&Vec3::new(-2.0, 0.0, 20.0), 0.5);
        let Err(PointRejection::InsideObstacle(_, name, Some(clear))) = &inside else {
            panic!("{inside:?}");
        };
        assert_eq!(name, "tower");
        assert!(world.check_point(clear, 0.5).is_ok());
        assert!(
            (clear - Vec3::new(-11.0, 0.0, 20.0)).norm() < 1e-9,
            "{clear}"
        );
        assert!(
            inside
                .map_err(|e| e.to_string())
                .is_err_and(|e| e.ends_with("; clear of it at that altitude: (-11.0, 0.0, 20.0)"))
        );
        // A tower that fills the area leaves nothing to suggest.
        let walled = World {
            bounds: Bounds {
                min: Vec3::new(-9.0, -9.0, 0.0),
                max: Vec3::new(9.0, 9.0, 60.0),
            },
            ..world
        };
        assert!(matches!(
            walled.check_point(&Vec3::new(1.0, 0.0, 20.0), 0.5),
            Err(PointRejection::InsideObstacle(_, _, None))
        ));
    }

    #[test]
    fn rejects_indefinite_and_asymmetric_matrices() {
        let indefinite = Matrix3::from_diagonal(&Vec3::new(1.0, -1.0, 1.0));
        assert_eq!(
            Ellipsoid::new("bad", Vec3::zeros(), indefinite),
            Err(EllipsoidError::NotPositiveDefinite("bad".into()))
        );
        let mut asym = Matrix3::identity();
        asym[(0, 1)] = 0.5;
        assert_eq!(
            Ellipsoid::new("bad", Vec3::zeros(), asym),
            Err(EllipsoidError::NotSymmetric("bad".into()))
        );
    }

    #[test]
    fn containment_and_inflation() {
        let t = tower();
        assert!(t.contains(&Vec3::new(9.0, 0.0, 10.0)));
        assert!(!t.contains(&Vec3::new(11.0, 0.0, 10.0)));
        assert!(t.inflated(2.0).contains(&Vec3::new(11.0, 0.0, 10.0)));
        let rotated = Ellipsoid::from_semi_axes(
            "r",
            Vec3::zeros(),
            Vec3::new(20.0, 2.0, 2.0),
            std::f64::consts::FRAC_PI_2,
        )
        .expect("valid");
        assert!(rotated.contains(&Vec3::new(0.0, 19.0, 0.0)));
        assert!(!rotated.contains(&Vec3::new(19.0, 0.0, 0.0)));
    }

    #[test]
    fn segments_through_and_past() {
        let t = tower();
        assert!(t.segment_intersects(&Vec3::new(-50.0, 0.0, 10.0), &Vec3::new(50.0, 0.0, 10.0)));
        assert!(!t.segment_intersects(&Vec3::new(-50.0, 20.0, 10.0), &Vec3::new(50.0, 20.0, 10.0)));
        assert!(!t.segment_intersects(&Vec3::new(-50.0, 0.0, 10.0), &Vec3::new(-20.0, 0.0, 10.0)));
    }

    #[test]
    fn clearance_bound_is_a_lower_bound() {
        let t = tower();
        let p = Vec3::new(25.0, 0.0, 0.0);
        let c = t.clearance_lower_bound(&p);
        assert!(c > 0.0 && c <= 15.0 + 1e-9, "{c}");
    }
}
