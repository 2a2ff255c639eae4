//! The whole simulated world without any I/O: the vehicles (each in its own NED frame at its
//! home), the targets, scripted and injected faults, the detection stand-in and the safety
//! statistics. `runtime` drives it with wall-clock time and carries its output to the network.

use crate::detection::{Detector, Observer};
use crate::faults::{self, FaultSchedule, LinkFaults};
use crate::link::{self, Handled};
use crate::targets::Target;
use crate::truth::{SafetyRules, SafetyStats};
use crate::vehicle::{Vehicle, VehicleParams};
use mavlink::dialects::common::MavMessage;
use tacos_shared::frames::{Home, ned_vector_to_enu};
use tacos_shared::messages::{SimTruth, TargetsMessage, VehicleTruth, WorldEvent};
use tacos_shared::scenario::{DroneSlot, FaultKind, FlightLimits, Scenario};
use tacos_shared::world::Bounds;
use tacos_shared::{DroneId, Vec3};

/// The physics step (sim seconds): 100 Hz.
pub const STEP: f64 = 0.01;

/// One vehicle slot: who it is, where its NED origin is, and its faults.
#[derive(Debug, Clone)]
pub struct SimVehicle {
    pub id: DroneId,
    /// MAVLink system id (slot index + 1).
    pub system_id: u8,
    pub home: Home,
    pub vehicle: Vehicle,
    pub faults: LinkFaults,
}

impl SimVehicle {
    pub fn position_enu(&self) -> Vec3 {
        self.home.ned_to_enu(&self.vehicle.position())
    }

    pub fn velocity_enu(&self) -> Vec3 {
        ned_vector_to_enu(&self.vehicle.velocity())
    }

    fn truth(&self, now: f64) -> VehicleTruth {
        VehicleTruth {
            drone: self.id.clone(),
            position: self.position_enu(),
            velocity: self.velocity_enu(),
            armed: self.vehicle.armed(),
            custom_mode: self.vehicle.custom_mode(),
            alive: self.vehicle.alive(),
            link_down: self.faults.dropped(now),
            landed: self.vehicle.landed(),
        }
    }
}

#[derive(Debug, Clone)]
pub struct Simulation {
    time: f64,
    limits: FlightLimits,
    bounds: Bounds,
    vehicles: Vec<SimVehicle>,
    targets: Vec<Target>,
    schedule: FaultSchedule,
    detector: Detector,
    rules: SafetyRules,
    stats: SafetyStats,
}

impl Simulation {
    /// The world of `scenario` with one vehicle per slot in `slots` (slot i = vehicle i, MAVLink
    /// system id i + 1). Slots beyond 255 get no vehicle: MAVLink system ids stop there.
    pub fn new(scenario: &Scenario, slots: &[DroneSlot]) -> Self {
        let params = VehicleParams::from_limits(&scenario.limits);
        let vehicles = slots
            .iter()
            .zip(1..=u8::MAX)
            .map(|(slot, system_id)| SimVehicle {
                id: slot.id.clone(),
                system_id,
                home: Home::new(slot.home),
                vehicle: Vehicle::new(params),
                faults: LinkFaults::default(),
            })
            .collect();
        Simulation {
            time: 0.0,
            limits: scenario.limits,
            bounds: scenario.world.bounds,
            vehicles,
            targets: scenario.targets.iter().map(Target::new).collect(),
            schedule: FaultSchedule::new(&scenario.faults),
            detector: Detector::default(),
            rules: SafetyRules::new(
                &scenario.world.obstacles,
                scenario.limits.drone_radius,
                scenario.limits.safety_distance,
            ),
            stats: SafetyStats::default(),
        }
    }

    /// Sim seconds since the start.
    pub fn time(&self) -> f64 {
        self.time
    }

    pub fn vehicles(&self) -> &[SimVehicle] {
        &self.vehicles
    }

    pub fn targets(&self) -> &[Target] {
        &self.targets
    }

    /// True when vehicle `i` exists and its MAVLink passes (alive, link not dropped).
    pub fn link_up(&self, i: usize) -> bool {
        self.vehicles
            .get(i)
            .is_some_and(|v| v.faults.link_up(self.time))
    }

    /// An incoming MAVLink message for vehicle `i`; `None` when the link is down (it never
    /// arrived).
    pub fn handle_mavlink(&mut self, i: usize, message: &MavMessage) -> Option<Handled> {
        if !self.link_up(i) {
            return None;
        }
        let v = self.vehicles.get_mut(i)?;
        Some(link::handle(&mut v.vehicle, v.system_id, message))
    }

    /// Injects a fault now; `None` when no vehicle has that id.
    pub fn inject(&mut self, drone: &DroneId, kind: FaultKind) -> Option<WorldEvent> {
        let now = self.time;
        let v = self.vehicles.iter_mut().find(|v| &v.id == drone)?;
        v.faults.apply(&kind, now);
        if kind == FaultKind::VehicleDies {
            v.vehicle.kill();
        }
        Some(WorldEvent::FaultInjected {
            drone: drone.clone(),
            fault: faults::describe(&kind),
        })
    }

    /// Advances by `dt` sim seconds in steps of at most [`STEP`]; returns what happened.
    pub fn advance(&mut self, dt: f64) -> Vec<WorldEvent> {
        let mut events = Vec::new();
        let mut left = dt;
        while left > 1e-9 {
            let h = left.min(STEP);
            self.step(h, &mut events);
            left -= h;
        }
        events
    }

    fn step(&mut self, dt: f64, events: &mut Vec<WorldEvent>) {
        self.time += dt;
        for fault in self.schedule.due(self.time) {
            // Faults naming a slot beyond the vehicles simulated in this run do not apply.
            if let Ok(drone) = DroneId::new(&fault.drone)
                && let Some(event) = self.inject(&drone, fault.kind)
            {
                events.push(event);
            }
        }
        let mut struck_ground = false;
        for v in &mut self.vehicles {
            v.vehicle.step(dt);
            if v.vehicle.take_ground_strike() {
                tracing::warn!(drone = %v.id, "flew into the ground under power: counted as an obstacle breach");
                struck_ground = true;
            }
        }

        let positions: Vec<Vec3> = self.vehicles.iter().map(SimVehicle::position_enu).collect();
        let airborne: Vec<Vec3> = self
            .vehicles
            .iter()
            .zip(&positions)
            .filter(|(v, _)| !v.vehicle.landed())
            .map(|(_, p)| *p)
            .collect();
        let alive_airborne: Vec<Vec3> = self
            .vehicles
            .iter()
            .zip(&positions)
            .filter(|(v, _)| v.vehicle.alive() && !v.vehicle.landed())
            .map(|(_, p)| *p)
            .collect();
        for t in &mut self.targets {
            t.step(dt, &self.bounds, &alive_airborne);
        }
        self.stats.update(&airborne, struck_ground, &self.rules);

        let observers: Vec<Observer<'_>> = self
            .vehicles
            .iter()
            .zip(&positions)
            .map(|(v, p)| Observer {
                drone: &v.id,
                position: *p,
                can_see: v.vehicle.alive() && !v.vehicle.landed(),
            })
            .collect();
        let hidden = self
            .targets
            .iter()
            .filter(|t| t.is_hidden())
            .map(|t| (t.name.as_str(), t.hidden_at.as_deref(), t.position));
        events.extend(self.detector.check(hidden, &observers, &self.limits));
    }

    /// Ground truth for `sim/truth`.
    pub fn truth(&self) -> SimTruth {
        SimTruth {
            sim_time: self.time,
            vehicles: self.vehicles.iter().map(|v| v.truth(self.time)).collect(),
            min_pair_distance: self.stats.min_pair_distance,
            min_obstacle_clearance: self.stats.min_obstacle_clearance,
            separation_breaches: self.stats.separation_breaches,
            obstacle_breaches: self.stats.obstacle_breaches,
        }
    }

    /// The visible targets for `world/targets`, stamped with sim time.
    pub fn targets_message(&self) -> TargetsMessage {
        TargetsMessage {
            stamp: self.time,
            targets: self
                .targets
                .iter()
                .filter(|t| t.is_observed(self.time))
                .map(Target::observation)
                .collect(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{
        COMMAND_LONG_DATA, MavCmd, MavFrame, MavResult, PositionTargetTypemask,
        SET_POSITION_TARGET_LOCAL_NED_DATA,
    };
    use tacos_shared::px4_mode::{self, Px4Mode};

    /// A small world: a tower in the middle, two drones with homes far from the origin, a
    /// hidden target at a car, a walking target, and a scripted link drop.
    const WORLD: &str = r#"
name = "t"
[limits]
takeoff_altitude = 4.0
max_speed = 4.0
max_accel = 3.0
drone_radius = 0.5
safety_distance = 2.0
detection_radius = 3.0
detection_altitude = 10.0
[bounds]
min = [-200.0, -200.0, 0.0]
max = [200.0, 200.0, 60.0]
[[obstacles]]
name = "tower"
center = [0.0, 0.0, 0.0]
semi_axes = [5.0, 5.0, 30.0]
[[landmarks]]
name = "car_1"
kind = "car"
position = [70.0, -105.0, 0.0]
[[drones]]
id = "alfa"
home = [60.0, -120.0, 0.0]
[[drones]]
id = "bravo"
home = [-60.0, 120.0, 0.0]
[[targets]]
name = "suspect"
hidden_at = "car_1"
[[targets]]
name = "walker"
start = [0.0, 50.0, 0.0]
motion = { type = "constant_velocity", velocity = [1.0, 0.0, 0.0] }
[[faults]]
at_s = 3.0
drone = "bravo"
kind = { link_drops = { duration_s = 2.0 } }
"#;

    fn sim() -> Simulation {
        let scenario = Scenario::from_toml(WORLD).expect("valid");
        Simulation::new(&scenario, &scenario.drones)
    }

    fn command(target_system: u8, command: MavCmd, params: [f32; 7]) -> MavMessage {
        MavMessage::COMMAND_LONG(COMMAND_LONG_DATA {
            param1: params[0],
            param2: params[1],
            param3: params[2],
            param4: params[3],
            param5: params[4],
            param6: params[5],
            param7: params[6],
            command,
            target_system,
            target_component: 1,
            confirmation: 0,
        })
    }

    fn result(handled: Option<Handled>) -> Option<MavResult> {
        match handled {
            Some(Handled::Command { result, .. }) => Some(result),
            _ => None,
        }
    }

    fn position_setpoint(ned: Vec3) -> MavMessage {
        MavMessage::SET_POSITION_TARGET_LOCAL_NED(SET_POSITION_TARGET_LOCAL_NED_DATA {
            time_boot_ms: 0,
            x: ned.x as f32,
            y: ned.y as f32,
            z: ned.z as f32,
            vx: 0.0,
            vy: 0.0,
            vz: 0.0,
            afx: 0.0,
            afy: 0.0,
            afz: 0.0,
            yaw: 0.0,
            yaw_rate: 0.0,
            type_mask: PositionTargetTypemask::from_bits_truncate(0b0000_1101_1111_1000),
            target_system: 1,
            target_component: 1,
            coordinate_frame: MavFrame::MAV_FRAME_LOCAL_NED,
        })
    }

    /// Streams `setpoint` to vehicle 0 at 20 Hz for `seconds`, collecting events.
    fn stream(
        s: &mut Simulation,
        setpoint: &MavMessage,
        seconds: f64,
        events: &mut Vec<WorldEvent>,
    ) {
        for _ in 0..(seconds / 0.05).round() as usize {
            s.handle_mavlink(0, setpoint);
            events.extend(s.advance(0.05));
        }
    }

    #[test]
    fn a_local_ned_setpoint_lands_at_the_right_world_place() {
        let mut s = sim();
        let arm = command(
            1,
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        assert_eq!(
            result(s.handle_mavlink(0, &arm)),
            Some(MavResult::MAV_RESULT_ACCEPTED)
        );
        let takeoff = command(
            1,
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, f32::NAN, f32::NAN, f32::NAN, 4.0],
        );
        assert_eq!(
            result(s.handle_mavlink(0, &takeoff)),
            Some(MavResult::MAV_RESULT_ACCEPTED)
        );
        s.advance(6.0);
        assert!((s.vehicles()[0].position_enu() - Vec3::new(60.0, -120.0, 4.0)).norm() < 0.15);

        // 10 m north, 5 m east of home, 4 m up: world (65, -110, 4).
        let mut events = Vec::new();
        let sp = position_setpoint(Vec3::new(10.0, 5.0, -4.0));
        stream(&mut s, &sp, 1.2, &mut events);
        let offboard = command(
            1,
            MavCmd::MAV_CMD_DO_SET_MODE,
            [
                1.0,
                f32::from(px4_mode::MAIN_OFFBOARD),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            ],
        );
        assert_eq!(
            result(s.handle_mavlink(0, &offboard)),
            Some(MavResult::MAV_RESULT_ACCEPTED)
        );
        stream(&mut s, &sp, 8.0, &mut events);
        let at = s.vehicles()[0].position_enu();
        assert!(
            (at - Vec3::new(65.0, -110.0, 4.0)).norm() < 0.1,
            "at {at:?}"
        );
        assert!(s.vehicles()[1].vehicle.landed(), "bravo never moved");

        // Passing within 3 m of car_1 at (70, -105) below 10 m: the suspect is detected by alfa.
        let sp = position_setpoint(Vec3::new(14.0, 9.0, -4.0));
        stream(&mut s, &sp, 4.0, &mut events);
        let detections: Vec<_> = events
            .iter()
            .filter(|e| matches!(e, WorldEvent::Detection { .. }))
            .collect();
        assert_eq!(detections.len(), 1, "{events:?}");
        assert!(
            matches!(detections[0], WorldEvent::Detection { drone, landmark: Some(l), .. }
            if drone.as_str() == "alfa" && l == "car_1")
        );
    }

    #[test]
    fn scripted_link_drop_blocks_mavlink_then_ends() {
        let mut s = sim();
        let events = s.advance(2.9);
        assert!(events.is_empty());
        assert!(s.link_up(1));
        let events = s.advance(0.2);
        assert_eq!(events.len(), 1);
        assert!(
            matches!(&events[0], WorldEvent::FaultInjected { drone, .. } if drone.as_str() == "bravo")
        );
        assert!(!s.link_up(1) && s.link_up(0));
        let arm = command(
            2,
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        assert!(s.handle_mavlink(1, &arm).is_none(), "dropped");
        assert!(!s.vehicles()[1].vehicle.armed());
        let truth = s.truth();
        assert!(truth.vehicles[1].link_down && truth.vehicles[1].alive);
        s.advance(2.0);
        assert!(s.link_up(1));
        assert_eq!(
            result(s.handle_mavlink(1, &arm)),
            Some(MavResult::MAV_RESULT_ACCEPTED)
        );
    }

    #[test]
    fn a_link_drop_in_offboard_ends_in_hold() {
        let mut s = sim();
        let alfa = DroneId::new("alfa").expect("valid");
        let arm = command(
            1,
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        s.handle_mavlink(0, &arm);
        let mut events = Vec::new();
        let sp = position_setpoint(Vec3::new(0.0, 0.0, -3.0));
        stream(&mut s, &sp, 1.2, &mut events);
        let offboard = command(
            1,
            MavCmd::MAV_CMD_DO_SET_MODE,
            [
                1.0,
                f32::from(px4_mode::MAIN_OFFBOARD),
                0.0,
                0.0,
                0.0,
                0.0,
                0.0,
            ],
        );
        assert_eq!(
            result(s.handle_mavlink(0, &offboard)),
            Some(MavResult::MAV_RESULT_ACCEPTED)
        );
        stream(&mut s, &sp, 3.0, &mut events);
        assert!(
            s.inject(&alfa, FaultKind::LinkDrops { duration_s: 5.0 })
                .is_some()
        );
        // The writer keeps streaming, but nothing gets through.
        stream(&mut s, &sp, 1.5, &mut events);
        assert_eq!(
            Px4Mode::from_custom_mode(s.truth().vehicles[0].custom_mode),
            Px4Mode::Hold
        );
        assert!(
            s.vehicles()[0].vehicle.armed() && !s.vehicles()[0].vehicle.landed(),
            "holding in the air"
        );
    }

    #[test]
    fn a_dead_vehicle_falls_and_is_reported() {
        let mut s = sim();
        let alfa = DroneId::new("alfa").expect("valid");
        let arm = command(
            1,
            MavCmd::MAV_CMD_COMPONENT_ARM_DISARM,
            [1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0],
        );
        s.handle_mavlink(0, &arm);
        let takeoff = command(
            1,
            MavCmd::MAV_CMD_NAV_TAKEOFF,
            [0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 4.0],
        );
        s.handle_mavlink(0, &takeoff);
        s.advance(5.0);
        let event = s
            .inject(&alfa, FaultKind::VehicleDies)
            .expect("alfa exists");
        assert!(matches!(event, WorldEvent::FaultInjected { .. }));
        assert!(
            s.inject(
                &DroneId::new("zulu").expect("valid"),
                FaultKind::VehicleDies
            )
            .is_none()
        );
        assert!(s.handle_mavlink(0, &arm).is_none());
        s.advance(3.0);
        let truth = s.truth();
        assert!(!truth.vehicles[0].alive && truth.vehicles[0].landed && !truth.vehicles[0].armed);
        assert!(truth.vehicles[0].position.z.abs() < 1e-9);
    }

    #[test]
    fn truth_and_targets_are_reported() {
        let mut s = sim();
        s.advance(1.0);
        let truth = s.truth();
        assert!((truth.sim_time - 1.0).abs() < 1e-6);
        assert_eq!(truth.vehicles.len(), 2);
        assert_eq!(truth.vehicles[0].position, Vec3::new(60.0, -120.0, 0.0));
        assert!(truth.min_pair_distance.is_infinite(), "nobody airborne yet");
        let targets = s.targets_message();
        assert_eq!(
            targets.targets.len(),
            1,
            "the hidden suspect is not published"
        );
        assert_eq!(targets.targets[0].name, "walker");
        assert!((targets.targets[0].position - Vec3::new(1.0, 50.0, 0.0)).norm() < 1e-6);
    }
}
