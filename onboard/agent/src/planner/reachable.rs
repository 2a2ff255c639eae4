//! Where a solve's control points can be, to drop the half-spaces that cannot be active: segment
//! k's control points stay within `max(max_speed, |v₀|) × (k + 1) dt` of the current position
//! (the speed bound) and within `|v₀| dt/2 + max_accel ((k + 1) dt)² / 2` of the coasting point
//! `p₀ + v₀ (k + ½) dt` (the acceleration bound). A half-space containing either ball holds for
//! every plan the QP can return. Used for the obstacles' and neighbours' half-spaces and for the
//! workspace's walls alike.

use super::constraints::HalfSpace;
use tacos_shared::Vec3;

/// Two balls per segment that its control points cannot leave.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Reachable {
    position: Vec3,
    /// Radius around the current position, per segment.
    reach: Vec<f64>,
    /// The coasting point and the radius around it, per segment.
    coast: Vec<(Vec3, f64)>,
}

impl Reachable {
    /// For `steps` segments of `dt` from the state (`position`, `velocity`).
    pub(crate) fn new(
        position: Vec3,
        velocity: Vec3,
        max_speed: f64,
        max_accel: f64,
        dt: f64,
        steps: usize,
    ) -> Reachable {
        let fastest = max_speed.max(velocity.norm());
        let reach = (0..steps)
            .map(|seg| fastest * (seg + 1) as f64 * dt + 1e-6)
            .collect();
        let coast = (0..steps)
            .map(|seg| {
                let t_end = (seg + 1) as f64 * dt;
                let centre = position + velocity * ((seg as f64 + 0.5) * dt);
                let radius = velocity.norm() * dt / 2.0 + 0.5 * max_accel * t_end * t_end;
                (centre, radius + 1e-6)
            })
            .collect();
        Reachable {
            position,
            reach,
            coast,
        }
    }

    /// True when no control point of segment `seg` can leave `half` (it contains one of the
    /// balls); false for a segment past the horizon.
    pub(crate) fn keeps_inside(&self, half: &HalfSpace, seg: usize) -> bool {
        let (Some(&reach), Some(&(centre, drift))) = (self.reach.get(seg), self.coast.get(seg))
        else {
            return false;
        };
        half.contains_ball(&self.position, reach) || half.contains_ball(&centre, drift)
    }
}
