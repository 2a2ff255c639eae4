//! The scenario's targets and how they move (world ENU). Visible targets are what
//! `world/targets` reports; hidden ones sit at a landmark until a drone detects them.

use tacos_shared::Vec3;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::{TargetMotion, TargetSpec};
use tacos_shared::world::Bounds;

/// One target's state.
#[derive(Debug, Clone, PartialEq)]
pub struct Target {
    pub name: String,
    pub kind: String,
    /// The landmark a hidden target hides at.
    pub hidden_at: Option<String>,
    pub position: Vec3,
    pub velocity: Vec3,
    motion: TargetMotion,
    observed_until_s: Option<f64>,
    /// Waypoint motion: the route (start, then the scenario's points) and the index of the
    /// point being headed for; `None` once a one-way route is finished.
    route: Vec<Vec3>,
    next: Option<usize>,
}

impl Target {
    pub fn new(spec: &TargetSpec) -> Self {
        let (route, next) = match &spec.motion {
            TargetMotion::Waypoints { points, .. } => {
                let mut route = vec![spec.start];
                route.extend(points.iter().copied());
                (route, Some(1))
            }
            _ => (Vec::new(), None),
        };
        let velocity = match spec.motion {
            TargetMotion::ConstantVelocity { velocity } => velocity,
            _ => Vec3::zeros(),
        };
        Target {
            name: spec.name.clone(),
            kind: spec.kind.clone(),
            hidden_at: spec.hidden_at.clone(),
            position: spec.start,
            velocity,
            motion: spec.motion.clone(),
            observed_until_s: spec.observed_until_s,
            route,
            next,
        }
    }

    pub fn is_hidden(&self) -> bool {
        self.hidden_at.is_some()
    }

    /// Whether `world/targets` reports this target at simulation time `t`.
    pub fn is_observed(&self, t: f64) -> bool {
        !self.is_hidden() && self.observed_until_s.is_none_or(|until| t < until)
    }

    pub fn observation(&self) -> TargetObservation {
        TargetObservation {
            name: self.name.clone(),
            position: self.position,
            velocity: self.velocity,
        }
    }

    /// Advances by `dt`; `drones` are the positions of the drones an evasive target runs from.
    pub fn step(&mut self, dt: f64, bounds: &Bounds, drones: &[Vec3]) {
        match self.motion.clone() {
            TargetMotion::Static => self.velocity = Vec3::zeros(),
            TargetMotion::Waypoints { speed, looped, .. } => self.follow_route(dt, speed, looped),
            TargetMotion::ConstantVelocity { .. } => self.bounce(dt, bounds),
            TargetMotion::Evasive { speed, flee_radius } => {
                self.flee(dt, bounds, drones, speed, flee_radius)
            }
        }
    }

    fn follow_route(&mut self, dt: f64, speed: f64, looped: bool) {
        let mut travel = speed * dt;
        // Unit direction of the last stretch travelled in this step.
        let mut heading = Vec3::zeros();
        // Several waypoints may be passed in one step when they are close together; bounded so a
        // degenerate route (all points equal) cannot spin forever.
        for _ in 0..=self.route.len() {
            let Some(i) = self.next else { break };
            let Some(&goal) = self.route.get(i) else {
                break;
            };
            let to_goal = goal - self.position;
            let distance = to_goal.norm();
            if distance > travel {
                heading = to_goal / distance;
                self.position += heading * travel;
                break;
            }
            self.position = goal;
            travel -= distance;
            self.next = if i + 1 < self.route.len() {
                Some(i + 1)
            } else if looped {
                Some(0)
            } else {
                None
            };
        }
        self.velocity = if self.next.is_some() {
            heading * speed
        } else {
            Vec3::zeros()
        };
    }

    fn bounce(&mut self, dt: f64, bounds: &Bounds) {
        self.position += self.velocity * dt;
        for i in 0..3 {
            if self.position[i] < bounds.min[i] {
                self.position[i] = (2.0 * bounds.min[i] - self.position[i]).min(bounds.max[i]);
                self.velocity[i] = self.velocity[i].abs();
            } else if self.position[i] > bounds.max[i] {
                self.position[i] = (2.0 * bounds.max[i] - self.position[i]).max(bounds.min[i]);
                self.velocity[i] = -self.velocity[i].abs();
            }
        }
    }

    /// Runs horizontally straight away from the nearest drone within `flee_radius`, sliding along
    /// the bounds rather than leaving them.
    fn flee(&mut self, dt: f64, bounds: &Bounds, drones: &[Vec3], speed: f64, flee_radius: f64) {
        let horizontal = |d: &Vec3| Vec3::new(self.position.x - d.x, self.position.y - d.y, 0.0);
        let threat = drones
            .iter()
            .map(horizontal)
            .filter(|away| away.norm() <= flee_radius)
            .min_by(|a, b| a.norm().total_cmp(&b.norm()));
        let Some(away) = threat else {
            self.velocity = Vec3::zeros();
            return;
        };
        // Right underneath: pick a fixed direction rather than dividing by zero.
        let direction = if away.norm() > 1e-6 {
            away / away.norm()
        } else {
            Vec3::x()
        };
        let mut velocity = direction * speed;
        for i in 0..2 {
            let next = self.position[i] + velocity[i] * dt;
            if next <= bounds.min[i] || next >= bounds.max[i] {
                velocity[i] = 0.0;
            }
        }
        // Cornered on one axis: run at full speed along the other.
        let v_norm = velocity.norm();
        if v_norm > 1e-9 {
            velocity *= speed / v_norm;
        }
        self.position += velocity * dt;
        for i in 0..3 {
            self.position[i] = self.position[i].clamp(bounds.min[i], bounds.max[i]);
        }
        self.velocity = velocity;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    const DT: f64 = 0.01;

    fn bounds() -> Bounds {
        Bounds {
            min: Vec3::new(-50.0, -50.0, 0.0),
            max: Vec3::new(50.0, 50.0, 40.0),
        }
    }

    fn spec(start: Vec3, motion: TargetMotion) -> TargetSpec {
        TargetSpec {
            name: "t".into(),
            kind: "person".into(),
            start,
            hidden_at: None,
            motion,
            observed_until_s: None,
        }
    }

    #[test]
    fn a_target_is_observed_until_its_time() {
        let mut s = spec(Vec3::zeros(), TargetMotion::Static);
        assert!(Target::new(&s).is_observed(1e6));
        s.observed_until_s = Some(10.0);
        let t = Target::new(&s);
        assert!(t.is_observed(9.9) && !t.is_observed(10.0));
        s.hidden_at = Some("car_1".into());
        assert!(
            !Target::new(&s).is_observed(0.0),
            "hidden targets never are"
        );
    }

    fn run(t: &mut Target, seconds: f64, drones: &[Vec3]) {
        for _ in 0..(seconds / DT).round() as usize {
            t.step(DT, &bounds(), drones);
        }
    }

    #[test]
    fn static_targets_stay() {
        let mut t = Target::new(&spec(Vec3::new(1.0, 2.0, 0.0), TargetMotion::Static));
        run(&mut t, 5.0, &[Vec3::new(1.0, 2.0, 3.0)]);
        assert_eq!(t.position, Vec3::new(1.0, 2.0, 0.0));
    }

    #[test]
    fn waypoints_are_followed_at_speed_and_loop() {
        let motion = TargetMotion::Waypoints {
            points: vec![Vec3::new(10.0, 0.0, 0.0), Vec3::new(10.0, 10.0, 0.0)],
            speed: 2.0,
            looped: true,
        };
        let mut t = Target::new(&spec(Vec3::zeros(), motion));
        run(&mut t, 2.5, &[]);
        assert!((t.position - Vec3::new(5.0, 0.0, 0.0)).norm() < 1e-6);
        assert!((t.velocity - Vec3::new(2.0, 0.0, 0.0)).norm() < 1e-9);
        run(&mut t, 5.0, &[]);
        assert!(
            (t.position - Vec3::new(10.0, 5.0, 0.0)).norm() < 1e-6,
            "{:?}",
            t.position
        );
        // The route back to the start is the diagonal (14.14 m): loop after ≈ 17.07 s in all.
        run(&mut t, 17.0711 - 7.5, &[]);
        assert!(
            t.position.norm() < 0.01,
            "back at the start: {:?}",
            t.position
        );
        run(&mut t, 1.0, &[]);
        assert!(
            (t.position - Vec3::new(2.0, 0.0, 0.0)).norm() < 0.02,
            "and round again"
        );
    }

    #[test]
    fn one_way_routes_stop_at_the_end() {
        let motion = TargetMotion::Waypoints {
            points: vec![Vec3::new(3.0, 4.0, 0.0)],
            speed: 1.0,
            looped: false,
        };
        let mut t = Target::new(&spec(Vec3::zeros(), motion));
        run(&mut t, 10.0, &[]);
        assert!((t.position - Vec3::new(3.0, 4.0, 0.0)).norm() < 1e-9);
        assert_eq!(t.velocity, Vec3::zeros());
    }

    #[test]
    fn constant_velocity_bounces_inside_the_bounds() {
        let motion = TargetMotion::ConstantVelocity {
            velocity: Vec3::new(10.0, -3.0, 0.0),
        };
        let mut t = Target::new(&spec(Vec3::new(45.0, 0.0, 0.0), motion));
        run(&mut t, 1.0, &[]);
        assert!(t.velocity.x < 0.0, "bounced off +x");
        assert!(
            (t.position.x - 45.0).abs() < 1e-6,
            "45 → 50 → 45: {}",
            t.position.x
        );
        for _ in 0..3000 {
            t.step(DT, &bounds(), &[]);
            assert!(bounds().contains(&t.position));
        }
    }

    #[test]
    fn evasive_targets_run_from_the_nearest_drone_and_stay_inside() {
        let motion = TargetMotion::Evasive {
            speed: 3.0,
            flee_radius: 30.0,
        };
        let mut t = Target::new(&spec(Vec3::new(40.0, 0.0, 0.0), motion));
        // Nobody near: it stays.
        run(&mut t, 1.0, &[Vec3::new(0.0, 0.0, 10.0)]);
        assert_eq!(t.position, Vec3::new(40.0, 0.0, 0.0));
        // A drone 5 m west of it: it runs east, then along the east wall.
        let drone = Vec3::new(35.0, -1.0, 10.0);
        t.step(DT, &bounds(), &[drone]);
        assert!(t.velocity.x > 2.5 && (t.velocity.norm() - 3.0).abs() < 1e-9);
        for _ in 0..1000 {
            t.step(DT, &bounds(), &[drone]);
            assert!(bounds().contains(&t.position));
        }
        assert!(t.position.x <= 50.0 && t.position.x > 49.9);
        assert!(
            t.position.y > 5.0,
            "slid north along the wall: {:?}",
            t.position
        );
    }
}
