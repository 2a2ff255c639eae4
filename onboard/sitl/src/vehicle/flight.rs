//! The vehicle in flight: what its position controller tracks in each mode, the floor and the
//! land detector, the auto-disarm timers, and a fall without power.

use super::{
    DISARM_AFTER_LANDING, DISARM_PREFLIGHT, GRAVITY, GROUND_CONTACT, HARD_TOUCHDOWN_SPEED, RETURN,
    TERMINAL_SPEED, Vehicle, text,
};
use crate::motion::Reference;
use mavlink::dialects::common::MavSeverity;
use tacos_shared::Vec3;
use tacos_shared::px4_mode::Px4Mode;

impl Vehicle {
    /// What the position controller tracks in the current mode.
    pub(super) fn reference(&self) -> Reference {
        match self.mode {
            Px4Mode::Takeoff => Reference::hold(self.takeoff_to),
            Px4Mode::Land => self.landing_reference(),
            Px4Mode::Offboard => self
                .setpoint
                .unwrap_or_else(|| Reference::hold(self.hold_at)),
            RETURN if self.return_landing => self.landing_reference(),
            RETURN => Reference::hold(Vec3::new(self.home.x, self.home.y, self.return_z)),
            _ => Reference::hold(self.hold_at),
        }
    }

    /// AUTO.LAND's descent over `land_at`.
    fn landing_reference(&self) -> Reference {
        let height = -self.body.position.z;
        // Slow down for the last metre, like PX4's MPC_LAND_ALT2.
        let speed = self.params.land_speed * height.clamp(0.4, 1.0);
        Reference {
            position: [Some(self.land_at.x), Some(self.land_at.y), None],
            velocity: [None, None, Some(speed)],
            acceleration: [None; 3],
        }
    }

    /// PX4's land detector: under offboard control, ground contact counts only while the
    /// setpoint asks for a descent of at least 1.1 × 0.9 × MPC_LAND_SPEED
    /// (`MulticopterLandDetector`'s `_in_descend`); a vehicle held on the floor by a still
    /// setpoint stays "in air".
    fn descent_commanded(&self) -> bool {
        if self.mode != Px4Mode::Offboard {
            return true;
        }
        let wanted = 1.1 * 0.9 * self.params.land_speed;
        self.setpoint
            .and_then(|r| r.velocity[2])
            .is_some_and(|down| down >= wanted)
    }

    /// The floor stops the body; the land detector decides whether it has landed.
    pub(super) fn check_ground_contact(&mut self) {
        if self.landed || self.body.velocity.z < 0.0 {
            return;
        }
        let near = self.body.position.z > -GROUND_CONTACT;
        let detected = near && self.descent_commanded();
        if detected || self.body.position.z >= 0.0 {
            self.struck_ground |= self.body.velocity.z > HARD_TOUCHDOWN_SPEED;
            self.body.position.z = 0.0;
            self.body.velocity = Vec3::zeros();
        }
        if detected {
            self.landed = true;
            self.armed_on_ground_since = self.time;
            self.home = self.body.position;
            self.say(MavSeverity::MAV_SEVERITY_INFO, text::LANDING_DETECTED);
            if self.mode == Px4Mode::Hold {
                self.hold_at = self.body.position;
            }
        }
    }

    pub(super) fn auto_disarm(&mut self) {
        if !(self.armed && self.landed) {
            return;
        }
        let (after, reason) = if self.flown_since_arming {
            (DISARM_AFTER_LANDING, text::DISARMED_LANDING)
        } else {
            (DISARM_PREFLIGHT, text::DISARMED_PREFLIGHT)
        };
        if self.time - self.armed_on_ground_since >= after - 1e-9 {
            self.on_disarmed(reason);
        }
    }

    /// Motors off in the air: gravity, some drag on the horizontal, until the ground.
    pub(super) fn fall(&mut self, dt: f64) {
        let v = self.body.velocity;
        let horizontal = Vec3::new(v.x, v.y, 0.0);
        let slow = (self.params.limits.max_accel * dt).min(horizontal.norm());
        let horizontal = if horizontal.norm() > 0.0 {
            horizontal * (1.0 - slow / horizontal.norm())
        } else {
            horizontal
        };
        let vz = (v.z + GRAVITY * dt).min(TERMINAL_SPEED);
        let new_v = Vec3::new(horizontal.x, horizontal.y, vz);
        self.body.position += (v + new_v) * (0.5 * dt);
        self.body.velocity = new_v;
        if self.body.position.z >= 0.0 {
            self.body.position.z = 0.0;
            self.body.velocity = Vec3::zeros();
            self.landed = true;
        }
    }
}
