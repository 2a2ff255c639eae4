//! A one-waypoint detour around the first obstacle that blocks the straight line to the goal.
//!
//! The QP only sees tangent half-spaces, so on its own a drone heading straight at a tower
//! stops in front of it (a local minimum: the goal pull is exactly along the plane's normal).
//! The detour moves the QP's reference to a point beside the obstacle: sideways (horizontally,
//! as drones prefer to go around rather than over a tall building), on the side the line
//! already passes, or to the right when it passes through the centre. The side is remembered
//! per obstacle until the line is clear so the reference does not flip from one side to the
//! other as the drone moves.

use tacos_shared::Vec3;
use tacos_shared::world::Ellipsoid;

/// Where the reference should go: `waypoint` first (if any), then the goal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Route {
    pub waypoint: Option<Vec3>,
}

/// Parameter in [0, 1] of the point of segment a→b with the smallest level, and that level.
fn closest_on_segment(e: &Ellipsoid, a: &Vec3, b: &Vec3) -> (f64, f64) {
    let d = a - e.center;
    let u = b - a;
    let au = e.shape * u;
    let quad = u.dot(&au);
    let t = if quad > 0.0 {
        (-d.dot(&au) / quad).clamp(0.0, 1.0)
    } else {
        0.0
    };
    (t, e.level(&(a + u * t)))
}

/// `keep_out` are the obstacles inflated by the drone radius (the hard limit), `clear` the same
/// inflated by a further margin (what the detour should leave between). `sides` holds the
/// remembered side per obstacle (+1 left, −1 right of the line from `from` to `to`, 0 none).
pub(crate) fn plan_route(
    from: &Vec3,
    to: &Vec3,
    keep_out: &[Ellipsoid],
    clear: &[Ellipsoid],
    sides: &mut [i8],
) -> Route {
    // The first obstacle (along the line) whose margin zone the line crosses. Lines that only
    // move away from an obstacle (closest point at `from`) are not blocked by it, and one the
    // drone (or the goal) is inside of is left to the QP's slack.
    let mut first: Option<(usize, f64)> = None;
    for (i, (hard, soft)) in keep_out.iter().zip(clear).enumerate() {
        let (t, level) = closest_on_segment(soft, from, to);
        let blocked = level <= 1.0 && t > 1e-9 && !hard.contains(from) && !hard.contains(to);
        if blocked {
            if first.is_none_or(|(_, best)| t < best) {
                first = Some((i, t));
            }
        } else if let Some(s) = sides.get_mut(i) {
            *s = 0;
        }
    }
    let Some((i, t)) = first else {
        return Route { waypoint: None };
    };
    let (hard, soft) = (&keep_out[i], &clear[i]);
    let line = to - from;
    let horizontal = Vec3::new(line.x, line.y, 0.0);
    let left = if horizontal.norm() > 1e-6 {
        Vec3::new(-horizontal.y, horizontal.x, 0.0) / horizontal.norm()
    } else {
        Vec3::x()
    };
    let closest = from + line * t;
    let side = match sides.get(i).copied().unwrap_or(0) {
        0 => {
            let offset = left.dot(&(closest - soft.center));
            if offset > 1e-3 { 1 } else { -1 }
        }
        s => s,
    };
    if let Some(s) = sides.get_mut(i) {
        *s = side;
    }
    let out = left * f64::from(side);
    // Slide sideways from the closest point until both legs clear: the first leg must miss
    // the hard zone (the drone may already be within the margin), the second the margin zone.
    let step = 0.5;
    for n in 1..=400 {
        let w = closest + out * (step * n as f64);
        if !soft.contains(&w)
            && !hard.segment_intersects(from, &w)
            && !soft.segment_intersects(&w, to)
        {
            return Route { waypoint: Some(w) };
        }
    }
    Route { waypoint: None }
}

/// The point at arc length `length` along `from → waypoint → to` (the end if shorter).
pub(crate) fn carrot(from: &Vec3, route: &Route, to: &Vec3, length: f64) -> (Vec3, bool) {
    let mut points = vec![*from];
    points.extend(route.waypoint);
    points.push(*to);
    let mut left = length.max(0.0);
    for pair in points.windows(2) {
        let seg = pair[1] - pair[0];
        let l = seg.norm();
        if l > left {
            return (pair[0] + seg * (left / l), true);
        }
        left -= l;
    }
    (*to, false)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tower() -> Ellipsoid {
        Ellipsoid::from_semi_axes(
            "t",
            Vec3::new(-18.0, -18.0, 0.0),
            Vec3::new(8.0, 8.0, 70.0),
            0.0,
        )
        .expect("valid")
    }

    #[test]
    fn detours_sideways_and_remembers_the_side() {
        let hard = [tower().inflated(0.75)];
        let soft = [tower().inflated(2.5)];
        let mut sides = [0i8];
        let from = Vec3::new(-18.0, -50.0, 15.0);
        let to = Vec3::new(-18.0, 5.0, 15.0);
        let r = plan_route(&from, &to, &hard, &soft, &mut sides);
        let w = r.waypoint.expect("blocked");
        // Straight through the centre: go right (heading +y, right is +x).
        assert!(w.x > -18.0 + 8.0, "{w:?}");
        assert!((w.z - 15.0).abs() < 1e-9);
        assert!(!hard[0].segment_intersects(&from, &w));
        assert!(!soft[0].segment_intersects(&w, &to));
        assert_eq!(sides, [-1]);
        // Slightly left of the centre now: the remembered side wins.
        let from2 = Vec3::new(-18.5, -45.0, 15.0);
        let r2 = plan_route(&from2, &to, &hard, &soft, &mut sides);
        assert!(r2.waypoint.is_some_and(|w| w.x > -10.0));
        // A clear line needs no waypoint and forgets the side.
        let r3 = plan_route(
            &Vec3::new(0.0, -50.0, 15.0),
            &Vec3::new(0.0, 5.0, 15.0),
            &hard,
            &soft,
            &mut sides,
        );
        assert_eq!(r3.waypoint, None);
        assert_eq!(sides, [0]);
    }

    #[test]
    fn carrot_walks_the_polyline() {
        let route = Route {
            waypoint: Some(Vec3::new(10.0, 0.0, 0.0)),
        };
        let to = Vec3::new(10.0, 10.0, 0.0);
        let (c, clipped) = carrot(&Vec3::zeros(), &route, &to, 15.0);
        assert!(clipped);
        assert!((c - Vec3::new(10.0, 5.0, 0.0)).norm() < 1e-12);
        assert_eq!(carrot(&Vec3::zeros(), &route, &to, 30.0), (to, false));
    }
}
