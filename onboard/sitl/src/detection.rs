//! The perception stand-in: a hidden target is "seen" the first time a live, airborne drone
//! passes within the detection radius (horizontally) at or below the detection altitude.

use std::collections::HashSet;
use tacos_shared::messages::WorldEvent;
use tacos_shared::scenario::FlightLimits;
use tacos_shared::{DroneId, Vec3};

/// A drone as the detector needs it.
#[derive(Debug, Clone, Copy)]
pub struct Observer<'a> {
    pub drone: &'a DroneId,
    /// World ENU.
    pub position: Vec3,
    pub can_see: bool,
}

/// Remembers which (target, drone) pairs have already been reported.
#[derive(Debug, Clone, Default)]
pub struct Detector {
    reported: HashSet<(String, DroneId)>,
}

impl Detector {
    /// The new detections of `hidden` targets (name, landmark, position) by `observers`.
    pub fn check<'t>(
        &mut self,
        hidden: impl IntoIterator<Item = (&'t str, Option<&'t str>, Vec3)>,
        observers: &[Observer<'_>],
        limits: &FlightLimits,
    ) -> Vec<WorldEvent> {
        let mut events = Vec::new();
        for (target, landmark, position) in hidden {
            for o in observers.iter().filter(|o| o.can_see) {
                let horizontal = (o.position.xy() - position.xy()).norm();
                let altitude = o.position.z - position.z;
                if horizontal <= limits.detection_radius
                    && altitude <= limits.detection_altitude
                    && self.reported.insert((target.to_owned(), o.drone.clone()))
                {
                    events.push(WorldEvent::Detection {
                        drone: o.drone.clone(),
                        target: target.to_owned(),
                        landmark: landmark.map(str::to_owned),
                        position,
                    });
                }
            }
        }
        events
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::scenario::Scenario;

    #[test]
    fn detected_once_per_drone_when_close_and_low() {
        let limits = Scenario::builtin("lab").expect("valid").limits;
        let (alfa, bravo) = (
            DroneId::new("alfa").expect("valid"),
            DroneId::new("bravo").expect("valid"),
        );
        let dog = ("dog", Some("small_park"), Vec3::new(-2.5, 2.5, 0.0));
        let mut d = Detector::default();
        let at = |drone, x: f64, z: f64, can_see| Observer {
            drone,
            position: Vec3::new(x, 2.5, z),
            can_see,
        };

        // Too far, too high, or not airborne: nothing.
        assert!(
            d.check([dog], &[at(&alfa, -1.0, 1.0, true)], &limits)
                .is_empty()
        );
        assert!(
            d.check([dog], &[at(&alfa, -2.5, 2.4, true)], &limits)
                .is_empty()
        );
        assert!(
            d.check([dog], &[at(&alfa, -2.5, 1.0, false)], &limits)
                .is_empty()
        );

        let events = d.check([dog], &[at(&alfa, -2.2, 1.0, true)], &limits);
        assert_eq!(events.len(), 1);
        assert!(
            matches!(&events[0], WorldEvent::Detection { drone, target, landmark: Some(l), .. }
                if drone == &alfa && target == "dog" && l == "small_park")
        );
        assert!(
            d.check([dog], &[at(&alfa, -2.2, 1.0, true)], &limits)
                .is_empty(),
            "once per drone"
        );
        assert_eq!(
            d.check([dog], &[at(&bravo, -2.5, 1.0, true)], &limits)
                .len(),
            1,
            "but each drone"
        );
    }
}
