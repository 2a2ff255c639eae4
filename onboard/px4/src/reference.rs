//! What the writer streams: the planner's newest setpoint, or a hold when the planner is silent.
//!
//! Rules (pure; the clock is passed in):
//! - a setpoint with a non-finite position, velocity or acceleration (or an infinite yaw) is
//!   rejected and counted; a NaN yaw means "keep heading";
//! - while the newest accepted setpoint is younger than the onboard timeout, it is streamed as is;
//! - after that, a hold at its position (velocity and acceleration zero, same yaw);
//! - before any setpoint ever arrived, a hold at the vehicle's current position once known: it
//!   follows the vehicle (so a takeoff in an AUTO mode leaves a sensible hold behind it) except
//!   while the vehicle is in OFFBOARD, where it stays put;
//! - with none of these, nothing: the writer never streams without a reference.

use crate::convert::EnuReference;
use std::time::{Duration, Instant};
use tacos_shared::Vec3;
use tacos_shared::ipc::SetpointSample;

/// Where the streamed reference comes from.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// The planner's newest setpoint.
    Planner,
    /// The planner went silent: hold at its last setpoint.
    HoldLastSetpoint,
    /// No setpoint ever arrived: hold where the vehicle is.
    HoldVehicle,
}

#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StreamReference {
    pub reference: EnuReference,
    pub source: Source,
}

/// What the writer knows of the vehicle, for the hold before any setpoint.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VehicleView {
    /// World ENU.
    pub position: Vec3,
    pub in_offboard: bool,
}

#[derive(Debug, Clone, Copy, PartialEq, thiserror::Error)]
#[error("setpoint {seq} rejected: non-finite values")]
pub struct RejectedSetpoint {
    pub seq: u64,
}

pub struct ReferenceKeeper {
    timeout: Duration,
    last: Option<(EnuReference, Instant)>,
    vehicle_hold: Option<Vec3>,
    rejected: u64,
}

impl ReferenceKeeper {
    pub fn new(onboard_timeout: Duration) -> Self {
        ReferenceKeeper {
            timeout: onboard_timeout,
            last: None,
            vehicle_hold: None,
            rejected: 0,
        }
    }

    /// Takes a setpoint from the planner, received at `now`.
    pub fn offer(&mut self, sample: &SetpointSample, now: Instant) -> Result<(), RejectedSetpoint> {
        if !sample.is_finite() || sample.yaw.is_infinite() {
            self.rejected += 1;
            return Err(RejectedSetpoint { seq: sample.seq });
        }
        let yaw = if sample.yaw.is_nan() {
            None
        } else {
            Some(sample.yaw)
        };
        let reference = EnuReference {
            position: sample.position(),
            velocity: sample.velocity(),
            acceleration: sample.acceleration(),
            yaw,
        };
        self.last = Some((reference, now));
        Ok(())
    }

    /// When the newest accepted setpoint arrived, if one ever did.
    pub fn last_setpoint_at(&self) -> Option<Instant> {
        self.last.map(|(_, at)| at)
    }

    /// How many setpoints were rejected so far.
    pub fn rejected(&self) -> u64 {
        self.rejected
    }

    /// The reference to stream at `now`, if any.
    pub fn current(
        &mut self,
        now: Instant,
        vehicle: Option<VehicleView>,
    ) -> Option<StreamReference> {
        if let Some((reference, received)) = self.last {
            return Some(if now.saturating_duration_since(received) < self.timeout {
                StreamReference {
                    reference,
                    source: Source::Planner,
                }
            } else {
                StreamReference {
                    reference: EnuReference::hold(reference.position, reference.yaw),
                    source: Source::HoldLastSetpoint,
                }
            });
        }
        if let Some(v) = vehicle
            && !(v.in_offboard && self.vehicle_hold.is_some())
        {
            self.vehicle_hold = Some(v.position);
        }
        self.vehicle_hold.map(|p| StreamReference {
            reference: EnuReference::hold(p, None),
            source: Source::HoldVehicle,
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const TIMEOUT: Duration = Duration::from_millis(500);

    fn ms(t0: Instant, ms: u64) -> Instant {
        t0 + Duration::from_millis(ms)
    }

    fn moving(seq: u64, p: [f64; 3]) -> SetpointSample {
        SetpointSample {
            seq,
            position: p,
            velocity: [1.0, -2.0, 0.5],
            acceleration: [0.1, 0.2, 0.3],
            yaw: 0.7,
            ..Default::default()
        }
    }

    #[test]
    fn nothing_is_streamed_without_a_reference() {
        let mut k = ReferenceKeeper::new(TIMEOUT);
        assert_eq!(k.current(Instant::now(), None), None);
    }

    #[test]
    fn planner_silence_turns_the_last_setpoint_into_a_hold() {
        let t0 = Instant::now();
        let mut k = ReferenceKeeper::new(TIMEOUT);
        assert!(k.offer(&moving(1, [1.0, 2.0, 3.0]), t0).is_ok());
        let live = k.current(ms(t0, 499), None);
        assert_eq!(live.map(|r| r.source), Some(Source::Planner));
        assert_eq!(
            live.map(|r| r.reference.velocity),
            Some(Vec3::new(1.0, -2.0, 0.5))
        );

        let held = k.current(ms(t0, 500), None);
        assert_eq!(
            held,
            Some(StreamReference {
                reference: EnuReference::hold(Vec3::new(1.0, 2.0, 3.0), Some(0.7)),
                source: Source::HoldLastSetpoint
            })
        );
        // Still a hold much later, and the vehicle's own position does not move it.
        let later = k.current(
            ms(t0, 60_000),
            Some(VehicleView {
                position: Vec3::new(9.0, 9.0, 9.0),
                in_offboard: true,
            }),
        );
        assert_eq!(later, held);

        // The planner comes back: its setpoint is streamed again at once.
        assert!(k.offer(&moving(2, [4.0, 5.0, 6.0]), ms(t0, 60_001)).is_ok());
        let back = k.current(ms(t0, 60_001), None);
        assert_eq!(
            back.map(|r| (r.source, r.reference.position)),
            Some((Source::Planner, Vec3::new(4.0, 5.0, 6.0)))
        );
    }

    #[test]
    fn non_finite_setpoints_are_rejected_and_counted() {
        let t0 = Instant::now();
        let mut k = ReferenceKeeper::new(TIMEOUT);
        assert!(k.offer(&moving(1, [1.0, 2.0, 3.0]), t0).is_ok());
        assert_eq!(
            k.offer(&moving(2, [f64::NAN, 2.0, 3.0]), t0),
            Err(RejectedSetpoint { seq: 2 })
        );
        let mut inf_vel = moving(3, [0.0; 3]);
        inf_vel.velocity[2] = f64::INFINITY;
        assert!(k.offer(&inf_vel, t0).is_err());
        let mut inf_yaw = moving(4, [0.0; 3]);
        inf_yaw.yaw = f64::NEG_INFINITY;
        assert!(k.offer(&inf_yaw, t0).is_err());
        assert_eq!(k.rejected(), 3);
        assert_eq!(
            k.current(t0, None).map(|r| r.reference.position),
            Some(Vec3::new(1.0, 2.0, 3.0))
        );

        let mut nan_yaw = moving(5, [7.0, 7.0, 7.0]);
        nan_yaw.yaw = f64::NAN;
        assert!(k.offer(&nan_yaw, t0).is_ok(), "NaN yaw means keep heading");
        assert_eq!(k.current(t0, None).map(|r| r.reference.yaw), Some(None));
    }

    #[test]
    fn before_any_setpoint_the_hold_follows_the_vehicle_until_offboard() {
        let t0 = Instant::now();
        let mut k = ReferenceKeeper::new(TIMEOUT);
        let at = |x: f64, in_offboard| {
            Some(VehicleView {
                position: Vec3::new(x, 0.0, 0.0),
                in_offboard,
            })
        };
        let pos = |r: Option<StreamReference>| {
            r.map(|r| (r.source, r.reference.position.x, r.reference.velocity))
        };
        assert_eq!(
            pos(k.current(t0, at(1.0, false))),
            Some((Source::HoldVehicle, 1.0, Vec3::zeros()))
        );
        assert_eq!(
            pos(k.current(t0, at(2.0, false))),
            Some((Source::HoldVehicle, 2.0, Vec3::zeros()))
        );
        // In offboard the hold is latched where it was.
        assert_eq!(
            pos(k.current(t0, at(3.0, true))),
            Some((Source::HoldVehicle, 2.0, Vec3::zeros()))
        );
        // Vehicle position lost: keep the hold.
        assert_eq!(
            pos(k.current(t0, None)),
            Some((Source::HoldVehicle, 2.0, Vec3::zeros()))
        );
    }
}
