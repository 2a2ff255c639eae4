//! Running safety statistics for `SimTruth`: closest approach between airborne vehicles, closest
//! approach to an obstacle, and how many simulation steps broke either margin.

use tacos_shared::Vec3;
use tacos_shared::world::Ellipsoid;

#[derive(Debug, Clone, PartialEq)]
pub struct SafetyStats {
    /// Infinity until two vehicles have been airborne together.
    pub min_pair_distance: f64,
    /// Infinity until a vehicle has been airborne (or when there are no obstacles).
    pub min_obstacle_clearance: f64,
    pub separation_breaches: u64,
    pub obstacle_breaches: u64,
}

impl Default for SafetyStats {
    fn default() -> Self {
        SafetyStats {
            min_pair_distance: f64::INFINITY,
            min_obstacle_clearance: f64::INFINITY,
            separation_breaches: 0,
            obstacle_breaches: 0,
        }
    }
}

/// What the statistics are measured against.
#[derive(Debug, Clone)]
pub struct SafetyRules {
    pub obstacles: Vec<Ellipsoid>,
    /// The obstacles grown by the drone radius.
    pub inflated: Vec<Ellipsoid>,
    pub safety_distance: f64,
}

impl SafetyRules {
    pub fn new(obstacles: &[Ellipsoid], drone_radius: f64, safety_distance: f64) -> Self {
        SafetyRules {
            obstacles: obstacles.to_vec(),
            inflated: obstacles.iter().map(|o| o.inflated(drone_radius)).collect(),
            safety_distance,
        }
    }
}

/// What one step broke, so the caller can say which drones and obstacles they were.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct StepBreaches {
    /// The closest pair too close: indices into `airborne` and their distance.
    pub separation: Option<(usize, usize, f64)>,
    /// The vehicle deepest into an obstacle grown by the drone radius: its index into
    /// `airborne`, the obstacle's index into `SafetyRules::obstacles`, and its clearance to the
    /// obstacle itself (below the drone radius).
    pub obstacle: Option<(usize, usize, f64)>,
}

impl SafetyStats {
    /// Folds in one simulation step; `airborne` are the world positions of the vehicles in the air,
    /// `struck_ground` whether a vehicle flew into the ground under power during the step (the
    /// ground counts as an obstacle). A step counts one separation breach however many pairs are
    /// too close, and likewise for obstacles.
    pub fn update(
        &mut self,
        airborne: &[Vec3],
        struck_ground: bool,
        rules: &SafetyRules,
    ) -> StepBreaches {
        let mut closest: Option<(usize, usize, f64)> = None;
        for (i, a) in airborne.iter().enumerate() {
            for (j, b) in airborne.iter().enumerate().skip(i + 1) {
                let d = (a - b).norm();
                self.min_pair_distance = self.min_pair_distance.min(d);
                if d < rules.safety_distance && closest.is_none_or(|(_, _, c)| d < c) {
                    closest = Some((i, j, d));
                }
            }
        }
        if closest.is_some() {
            self.separation_breaches += 1;
        }
        let mut deepest: Option<(usize, usize, f64)> = None;
        for (i, p) in airborne.iter().enumerate() {
            for (k, (o, grown)) in rules.obstacles.iter().zip(&rules.inflated).enumerate() {
                let clearance = o.clearance_lower_bound(p);
                self.min_obstacle_clearance = self.min_obstacle_clearance.min(clearance);
                if grown.contains(p) && deepest.is_none_or(|(_, _, c)| clearance < c) {
                    deepest = Some((i, k, clearance));
                }
            }
        }
        if deepest.is_some() || struck_ground {
            self.obstacle_breaches += 1;
        }
        StepBreaches {
            separation: closest,
            obstacle: deepest,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rules() -> SafetyRules {
        let tower =
            Ellipsoid::from_semi_axes("tower", Vec3::zeros(), Vec3::new(5.0, 5.0, 30.0), 0.0)
                .expect("valid");
        SafetyRules::new(&[tower], 0.5, 2.0)
    }

    #[test]
    fn nothing_airborne_leaves_the_stats_untouched() {
        let mut s = SafetyStats::default();
        s.update(&[], false, &rules());
        assert_eq!(s, SafetyStats::default());
    }

    #[test]
    fn pairs_and_obstacles_are_measured() {
        let rules = rules();
        let mut s = SafetyStats::default();
        s.update(
            &[Vec3::new(20.0, 0.0, 5.0), Vec3::new(23.0, 0.0, 5.0)],
            false,
            &rules,
        );
        assert!((s.min_pair_distance - 3.0).abs() < 1e-12);
        assert_eq!((s.separation_breaches, s.obstacle_breaches), (0, 0));
        assert!(s.min_obstacle_clearance > 10.0 && s.min_obstacle_clearance.is_finite());

        let step = s.update(
            &[Vec3::new(20.0, 0.0, 5.0), Vec3::new(21.0, 0.0, 5.0)],
            false,
            &rules,
        );
        assert_eq!(s.separation_breaches, 1);
        assert_eq!(step.separation.map(|(i, j, _)| (i, j)), Some((0, 1)));
        assert_eq!(step.obstacle, None);
        // 5.3 m from the centre: outside the tower (5 m) but inside it grown by 0.5 m.
        let step = s.update(
            &[Vec3::new(40.0, 0.0, 0.0), Vec3::new(5.3, 0.0, 0.0)],
            false,
            &rules,
        );
        assert_eq!(s.obstacle_breaches, 1);
        let (drone, obstacle, clearance) = step.obstacle.expect("the breach is named");
        assert_eq!((drone, obstacle), (1, 0));
        assert!(clearance > 0.0 && clearance <= 0.3 + 1e-9, "{clearance}");
        assert!(s.min_obstacle_clearance > 0.0 && s.min_obstacle_clearance <= 0.3 + 1e-9);
        // Running minima do not go back up.
        s.update(
            &[Vec3::new(40.0, 0.0, 5.0), Vec3::new(0.0, 40.0, 5.0)],
            false,
            &rules,
        );
        assert!((s.min_pair_distance - 1.0).abs() < 1e-12);
        // Flying into the ground is an obstacle breach, even with nothing airborne after it.
        s.update(&[], true, &rules);
        assert_eq!(s.obstacle_breaches, 2);
    }
}
