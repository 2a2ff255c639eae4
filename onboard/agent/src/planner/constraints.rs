//! Pure geometry of the planner's linear constraints: tangent half-spaces of ellipsoid obstacles,
//! separating half-spaces between two drones in the downwash-scaled metric, and the
//! time-aligned reading of a published path.

use tacos_shared::Vec3;
use tacos_shared::world::Ellipsoid;

/// `{x : normal·x ≥ offset}` with a unit `normal`, so signed distances are in metres.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HalfSpace {
    pub normal: Vec3,
    pub offset: f64,
}

impl HalfSpace {
    /// Normalises `normal`; `None` when it is zero or not finite.
    pub fn new(normal: Vec3, offset: f64) -> Option<HalfSpace> {
        let n = normal.norm();
        if !(n.is_finite() && n > 1e-12 && offset.is_finite()) {
            return None;
        }
        Some(HalfSpace {
            normal: normal / n,
            offset: offset / n,
        })
    }

    /// Positive inside, negative outside, in metres.
    pub fn signed_distance(&self, x: &Vec3) -> f64 {
        self.normal.dot(x) - self.offset
    }

    pub fn contains(&self, x: &Vec3, tolerance: f64) -> bool {
        self.signed_distance(x) >= -tolerance
    }

    /// True when every point within `radius` of `centre` is inside (the constraint is then
    /// redundant for anything that cannot leave that ball).
    pub fn contains_ball(&self, centre: &Vec3, radius: f64) -> bool {
        self.signed_distance(centre) >= radius
    }
}

/// The tangent half-space of `ellipsoid` at the point where the ray from its centre through
/// `towards` meets its surface, oriented away from the ellipsoid. By convexity the whole
/// ellipsoid lies on the other side, so any point inside the half-space is outside it.
/// When `towards` is the centre itself, `fallback` (or +x) gives the ray's direction.
pub fn tangent_half_space(ellipsoid: &Ellipsoid, towards: &Vec3, fallback: &Vec3) -> HalfSpace {
    let a = &ellipsoid.shape;
    let pick = |d: Vec3| {
        let level = d.dot(&(a * d));
        (level.is_finite() && level > 1e-18).then_some((d, level))
    };
    let (d, level) = pick(towards - ellipsoid.center)
        .or_else(|| pick(*fallback))
        .unwrap_or((Vec3::x(), a[(0, 0)].max(f64::MIN_POSITIVE)));
    let surface = ellipsoid.center + d / level.sqrt();
    let gradient = a * (surface - ellipsoid.center);
    let offset = gradient.dot(&surface);
    // The gradient of a positive-definite form at a surface point is never zero; the fallback
    // only guards against a degenerate matrix.
    HalfSpace::new(gradient, offset).unwrap_or(HalfSpace {
        normal: Vec3::x(),
        offset: ellipsoid.center.x + 1.0 / a[(0, 0)].max(f64::MIN_POSITIVE).sqrt(),
    })
}

/// The downwash-scaled metric: vertical offsets count `1 / factor` of horizontal ones, so a
/// separation `d` in this metric means `d` horizontally but `factor × d` vertically.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Downwash {
    factor: f64,
}

impl Downwash {
    /// `factor` ≥ 1 (smaller values are raised to 1: the metric never shrinks horizontal
    /// separation, so a scaled distance is never more than the Euclidean one).
    pub fn new(factor: f64) -> Downwash {
        let factor = if factor.is_finite() {
            factor.max(1.0)
        } else {
            1.0
        };
        Downwash { factor }
    }

    pub fn scale(&self, v: &Vec3) -> Vec3 {
        Vec3::new(v.x, v.y, v.z / self.factor)
    }

    pub fn distance(&self, a: &Vec3, b: &Vec3) -> f64 {
        self.scale(&(a - b)).norm()
    }
}

/// My side of a separating half-space between me (at `mine`) and a neighbour (at `theirs`).
///
/// In the scaled space `y = S x` the normal `m` points from me to the neighbour, rotated by
/// `right_hand` radians counter-clockwise about z (so both drones veer to their right: the
/// neighbour builds the exact opposite half-space), through the scaled midpoint; my side keeps
/// `keep` (half the safety distance plus margins) from it. If both drones keep `keep ≥ d/2`,
/// any two points on their sides are at least `d` apart in the scaled metric, hence at least
/// `d` apart in Euclidean distance. `fallback` is the direction to use (from me to them) when
/// the two points coincide.
///
/// `their_share` places the plane between us: ½ for a neighbour that keeps its own side (the
/// midpoint), 1 for one that cannot give way (through its point, so `keep` must then be the
/// whole distance).
pub fn separating_half_space(
    mine: &Vec3,
    theirs: &Vec3,
    keep: f64,
    their_share: f64,
    metric: &Downwash,
    right_hand: f64,
    fallback: &Vec3,
) -> HalfSpace {
    let ya = metric.scale(mine);
    let yb = metric.scale(theirs);
    let diff = yb - ya;
    let dir = if diff.norm() > 1e-9 {
        diff / diff.norm()
    } else {
        let f = metric.scale(fallback);
        if f.norm() > 1e-12 {
            f / f.norm()
        } else {
            Vec3::x()
        }
    };
    let (s, c) = right_hand.sin_cos();
    let m = Vec3::new(dir.x * c - dir.y * s, dir.x * s + dir.y * c, dir.z);
    let mid = ya + (yb - ya) * their_share;
    // m·(S x) ≤ m·mid − keep  ⇔  (−S m)·x ≥ keep − m·mid   (S is diagonal).
    let normal = -metric.scale(&m);
    let offset = keep - m.dot(&mid);
    HalfSpace::new(normal, offset).unwrap_or(HalfSpace {
        normal: -Vec3::x(),
        offset: keep - mid.x,
    })
}

/// The position on a path of `positions` spaced `dt` apart, `t` seconds after its first point:
/// linear between points, the first point before it starts and the last after it ends. Every
/// drone reads its own and its neighbours' published paths through this one function, so two
/// drones build their separating half-spaces from the same pair of points.
pub fn path_point(positions: &[Vec3], dt: f64, t: f64) -> Option<Vec3> {
    let first = *positions.first()?;
    let last = *positions.last()?;
    if !(dt > 0.0 && t.is_finite()) || t <= 0.0 {
        return Some(first);
    }
    let x = t / dt;
    let i = x.floor();
    if i >= (positions.len() - 1) as f64 {
        return Some(last);
    }
    let i = i as usize;
    let f = x - i as f64;
    Some(positions[i] * (1.0 - f) + positions[i + 1] * f)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A small deterministic generator (no external crates needed in tests).
    struct Lcg(u64);
    impl Lcg {
        fn unit(&mut self) -> f64 {
            self.0 = self
                .0
                .wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407);
            ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
        }
        fn range(&mut self, lo: f64, hi: f64) -> f64 {
            lo + (hi - lo) * self.unit()
        }
        fn direction(&mut self) -> Vec3 {
            loop {
                let v = Vec3::new(
                    self.range(-1.0, 1.0),
                    self.range(-1.0, 1.0),
                    self.range(-1.0, 1.0),
                );
                let n = v.norm();
                if n > 1e-3 && n <= 1.0 {
                    return v / n;
                }
            }
        }
    }

    fn surface_points(e: &Ellipsoid, rng: &mut Lcg, n: usize) -> Vec<Vec3> {
        let (axes, dirs) = e.principal_axes();
        (0..n)
            .map(|_| {
                let u = rng.direction();
                e.center + dirs * Vec3::new(u.x * axes.x, u.y * axes.y, u.z * axes.z)
            })
            .collect()
    }

    #[test]
    fn tangent_planes_touch_and_keep_the_ellipsoid_out() {
        let mut rng = Lcg(7);
        let obstacles = [
            Ellipsoid::from_semi_axes(
                "tower",
                Vec3::new(18.0, 18.0, 0.0),
                Vec3::new(8.0, 8.0, 70.0),
                0.0,
            ),
            Ellipsoid::from_semi_axes(
                "slab",
                Vec3::new(-3.0, 5.0, 10.0),
                Vec3::new(12.0, 2.0, 4.0),
                0.7,
            ),
        ];
        for o in obstacles {
            let o = o.expect("valid").inflated(0.5);
            let surface = surface_points(&o, &mut rng, 2000);
            for _ in 0..200 {
                let towards = o.center + rng.direction() * rng.range(0.1, 60.0);
                let h = tangent_half_space(&o, &towards, &Vec3::x());
                // It touches: some surface point on the plane (the ray's), and the ray's point
                // is on the ellipsoid's surface.
                let d = towards - o.center;
                let touch = o.center + d / o.level(&towards).sqrt();
                assert!((o.level(&touch) - 1.0).abs() < 1e-9);
                assert!(h.signed_distance(&touch).abs() < 1e-9);
                // Every surface point is on the far side (or on the plane).
                for s in &surface {
                    assert!(h.signed_distance(s) <= 1e-9, "{s:?} is inside {h:?}");
                }
                // The linearisation point is inside the half-space iff it is outside.
                if o.level(&towards) > 1.0 + 1e-9 {
                    assert!(h.signed_distance(&towards) > 0.0);
                } else if o.level(&towards) < 1.0 - 1e-9 {
                    assert!(h.signed_distance(&towards) < 0.0);
                }
            }
            // Degenerate: through the centre uses the fallback direction.
            let h = tangent_half_space(&o, &o.center, &Vec3::z());
            assert!(h.normal.dot(&Vec3::z()) > 0.0);
        }
    }

    #[test]
    fn separating_half_spaces_keep_the_safety_distance() {
        let mut rng = Lcg(11);
        let metric = Downwash::new(2.5);
        let d = 3.0;
        let mut checked = 0;
        for case in 0..200 {
            let a = Vec3::new(
                rng.range(-10.0, 10.0),
                rng.range(-10.0, 10.0),
                rng.range(0.0, 20.0),
            );
            let b = a + rng.direction() * rng.range(0.0, 12.0);
            let angle = if case % 2 == 0 { 0.0 } else { 0.3 };
            let mine = separating_half_space(&a, &b, d / 2.0, 0.5, &metric, angle, &(b - a));
            let theirs = separating_half_space(&b, &a, d / 2.0, 0.5, &metric, angle, &(a - b));
            // The two normals are opposite: the half-spaces are parallel.
            assert!(
                (mine.normal + theirs.normal).norm() < 1e-9,
                "{mine:?} {theirs:?}"
            );
            for _ in 0..400 {
                let x = (a + b) * 0.5 + rng.direction() * rng.range(0.0, 15.0);
                let y = (a + b) * 0.5 + rng.direction() * rng.range(0.0, 15.0);
                if mine.contains(&x, 0.0) && theirs.contains(&y, 0.0) {
                    checked += 1;
                    assert!(metric.distance(&x, &y) >= d - 1e-9);
                    assert!((x - y).norm() >= d - 1e-9);
                }
            }
            // The closest pair: project from the midpoint onto both planes along the normals.
            let mid = (a + b) * 0.5;
            let x = mid + mine.normal * (-mine.signed_distance(&mid));
            let y = mid + theirs.normal * (-theirs.signed_distance(&mid));
            assert!(metric.distance(&x, &y) >= d - 1e-9);
        }
        // The random pairs did exercise the check.
        assert!(checked > 1000, "{checked}");
        // Vertical neighbours need downwash-factor times the distance.
        let a = Vec3::new(0.0, 0.0, 10.0);
        let b = Vec3::new(0.0, 0.0, 20.0);
        let mine = separating_half_space(&a, &b, d / 2.0, 0.5, &metric, 0.0, &(b - a));
        let boundary = mine.offset / mine.normal.z;
        assert!(
            (boundary - (15.0 - 2.5 * d / 2.0)).abs() < 1e-9,
            "{boundary}"
        );
    }

    #[test]
    fn a_plane_against_a_neighbour_that_cannot_give_way_passes_through_its_point() {
        let metric = Downwash::new(2.0);
        let a = Vec3::new(0.0, 0.0, 10.0);
        let b = Vec3::new(4.0, 0.0, 10.0);
        let mine = separating_half_space(&a, &b, 3.0, 1.0, &metric, 0.0, &(b - a));
        // My side ends 3 m short of the neighbour itself, not of the midpoint.
        assert!((mine.signed_distance(&Vec3::new(1.0, 0.0, 10.0))).abs() < 1e-9);
        assert!(mine.contains(&a, 0.0));
        assert!(!mine.contains(&Vec3::new(1.5, 0.0, 10.0), 0.0));
    }

    #[test]
    fn paths_are_read_with_time_alignment() {
        let path = [
            Vec3::zeros(),
            Vec3::new(1.0, 0.0, 0.0),
            Vec3::new(2.0, 2.0, 0.0),
        ];
        assert_eq!(path_point(&path, 0.1, -1.0), Some(Vec3::zeros()));
        let p = path_point(&path, 0.1, 0.05).expect("non-empty");
        assert!((p - Vec3::new(0.5, 0.0, 0.0)).norm() < 1e-12);
        let p = path_point(&path, 0.1, 0.15).expect("non-empty");
        assert!((p - Vec3::new(1.5, 1.0, 0.0)).norm() < 1e-12);
        assert_eq!(path_point(&path, 0.1, 5.0), Some(Vec3::new(2.0, 2.0, 0.0)));
        assert_eq!(path_point(&[], 0.1, 0.0), None);
    }
}
