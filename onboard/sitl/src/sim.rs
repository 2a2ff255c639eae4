//! The whole simulated world without any I/O: the vehicles (each in its own NED frame at its
//! home), the targets, scripted and injected faults, the detection stand-in and the safety
//! statistics. `runtime` drives it with wall-clock time and carries its output to the network.

use crate::config::Px4Options;
use crate::detection::{Detector, Observer};
use crate::faults::{self, FaultSchedule, LinkFaults};
use crate::geo::LocalFrame;
use crate::link::{self, Handled};
use crate::observed::ObservedVehicle;
use crate::streams::Streams;
use crate::targets::Target;
use crate::telemetry;
use crate::truth::{SafetyRules, SafetyStats, StepBreaches};
use crate::vehicle::{Vehicle, VehicleParams};
use mavlink::MavHeader;
use mavlink::dialects::common::MavMessage;
use tacos_shared::frames::{Home, ned_vector_to_enu};
use tacos_shared::messages::{SimTruth, TargetsMessage, VehicleTruth, WorldEvent};
use tacos_shared::scenario::{DroneSlot, FaultKind, FlightLimits, Scenario};
use tacos_shared::world::Bounds;
use tacos_shared::{DroneId, Vec3};

/// The physics step (sim seconds): 100 Hz.
pub const STEP: f64 = 0.01;

/// One vehicle slot: who it is, where its NED origin is, its link's streams, and its faults.
#[derive(Debug, Clone)]
pub struct SimVehicle {
    pub id: DroneId,
    /// MAVLink system id (slot index + 1).
    pub system_id: u8,
    /// The spawn point: the origin of the vehicle's local NED frame (PX4's EKF origin; its
    /// *home* moves, see [`Vehicle::home`]).
    pub home: Home,
    pub frame: LocalFrame,
    pub vehicle: Vehicle,
    pub streams: Streams,
    pub faults: LinkFaults,
    /// The id of the next chunked STATUSTEXT.
    next_text_id: u16,
}

/// What an incoming MAVLink message did, and the messages that answer it, in order.
#[derive(Debug, Clone, PartialEq)]
pub struct Response {
    pub handled: Handled,
    pub replies: Vec<MavMessage>,
}

impl SimVehicle {
    /// The vehicle's pending STATUSTEXTs as messages (long ones in chunks).
    fn status_texts(&mut self) -> Vec<MavMessage> {
        let mut out = Vec::new();
        for text in self.vehicle.take_status_texts() {
            let chunks = telemetry::statustexts(&text, self.next_text_id);
            if chunks.len() > 1 {
                self.next_text_id = self.next_text_id.wrapping_add(1).max(1);
            }
            out.extend(chunks);
        }
        out
    }

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
    /// Real vehicles (PX4 SITL) the world only observes; with them, `vehicles` is empty.
    observed: Vec<ObservedVehicle>,
    targets: Vec<Target>,
    schedule: FaultSchedule,
    detector: Detector,
    rules: SafetyRules,
    stats: SafetyStats,
    /// What the last step broke: a breach is logged when it begins.
    last_breaches: StepBreaches,
}

impl Simulation {
    /// The world of `scenario` with one vehicle per slot in `slots` (slot i = vehicle i, MAVLink
    /// system id i + 1), set up with PX4's defaults. Slots beyond 255 get no vehicle: MAVLink
    /// system ids stop there.
    pub fn new(scenario: &Scenario, slots: &[DroneSlot]) -> Self {
        Self::with_px4(scenario, slots, &Px4Options::default())
    }

    /// [`Simulation::new`] with the vehicles set up by `px4`.
    pub fn with_px4(scenario: &Scenario, slots: &[DroneSlot], px4: &Px4Options) -> Self {
        let params = VehicleParams {
            readiness_delay: px4.readiness_delay_s,
            ..VehicleParams::from_limits(&scenario.limits)
        };
        let vehicles = slots
            .iter()
            .zip(1..=u8::MAX)
            .map(|(slot, system_id)| {
                let frame = LocalFrame {
                    origin: px4.origin,
                    spawn_enu: slot.home,
                };
                SimVehicle {
                    id: slot.id.clone(),
                    system_id,
                    home: Home::new(slot.home),
                    frame,
                    vehicle: Vehicle::new(VehicleParams {
                        ground_amsl: frame.ground_amsl(),
                        ..params
                    }),
                    streams: Streams::new(px4.link_profile, 0.0),
                    faults: LinkFaults::default(),
                    next_text_id: 1,
                }
            })
            .collect();
        Simulation {
            time: 0.0,
            limits: scenario.limits,
            bounds: scenario.world.bounds,
            vehicles,
            observed: Vec::new(),
            targets: scenario.targets.iter().map(Target::new).collect(),
            schedule: FaultSchedule::new(&scenario.faults),
            detector: Detector::default(),
            rules: SafetyRules::new(
                &scenario.world.obstacles,
                scenario.limits.drone_radius,
                scenario.limits.safety_distance,
            ),
            stats: SafetyStats::default(),
            last_breaches: StepBreaches::default(),
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

    /// An incoming MAVLink message for vehicle `i` from `header`'s sender; `None` when the link
    /// is down (it never arrived). The replies are what PX4 sends back at once: for a command,
    /// the ACKs (addressed to the sender), a requested message, and the STATUSTEXTs saying why.
    pub fn handle_mavlink(
        &mut self,
        i: usize,
        header: &MavHeader,
        message: &MavMessage,
    ) -> Option<Response> {
        if !self.link_up(i) {
            return None;
        }
        let now = self.time;
        let v = self.vehicles.get_mut(i)?;
        let sender = (
            u8::try_from(header.system_id).unwrap_or(0),
            header.component_id,
        );
        let handled = link::handle_from(
            &mut v.vehicle,
            &mut v.streams,
            v.system_id,
            sender,
            message,
            now,
        );
        let mut replies = Vec::new();
        if let Handled::Command {
            command,
            results,
            requested,
        } = &handled
        {
            // A sender id beyond 255 cannot be addressed; 0 is the broadcast.
            let target_system = u8::try_from(header.system_id).unwrap_or(0);
            let ack =
                |result| link::command_ack(*command, result, target_system, header.component_id);
            // All acks but the last (DO_SET_MODE's first, from PX4's MAVLink receiver) go at once;
            // the requested message, the texts and the final result follow.
            if let Some((last, first)) = results.split_last() {
                replies.extend(first.iter().map(|r| ack(*r)));
                if let Some(stream) = requested {
                    replies.push(telemetry::stream_message(*stream, &v.vehicle, &v.frame));
                }
                replies.extend(v.status_texts());
                replies.push(ack(*last));
            }
        }
        Some(Response { handled, replies })
    }

    /// The messages vehicle `i` sends now: pending STATUSTEXTs, then the streams that are due.
    /// Nothing (and the texts are lost) while its link is down.
    pub fn telemetry(&mut self, i: usize) -> Vec<MavMessage> {
        let up = self.link_up(i);
        let now = self.time;
        let Some(v) = self.vehicles.get_mut(i) else {
            return Vec::new();
        };
        let mut out = v.status_texts();
        if !up {
            return Vec::new();
        }
        for stream in v.streams.due(now) {
            out.push(telemetry::stream_message(stream, &v.vehicle, &v.frame));
        }
        out
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

    /// The world of `scenario` around real vehicles it does not simulate (`--observe-px4-*`):
    /// their truth is what each reports on its own MAVLink link ([`Simulation::observe`]).
    pub fn observing(scenario: &Scenario, observed: Vec<ObservedVehicle>) -> Self {
        let mut sim = Self::new(scenario, &[]);
        sim.observed = observed;
        sim
    }

    pub fn observed(&self) -> &[ObservedVehicle] {
        &self.observed
    }

    /// A message heard from observed vehicle `i`.
    pub fn observe(&mut self, i: usize, header: &MavHeader, message: &MavMessage) {
        let now = self.time;
        if let (Some(v), Ok(sysid)) = (self.observed.get_mut(i), u8::try_from(header.system_id)) {
            v.on_message(sysid, header.component_id, message, now);
        }
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

        let fleet = fleet(&self.vehicles, &self.observed, self.time);
        let airborne_ids: Vec<(&DroneId, Vec3)> = fleet
            .iter()
            .filter(|(_, _, _, landed)| !landed)
            .map(|(id, p, _, _)| (*id, *p))
            .collect();
        let airborne: Vec<Vec3> = airborne_ids.iter().map(|(_, p)| *p).collect();
        let alive_airborne: Vec<Vec3> = fleet
            .iter()
            .filter(|(_, _, alive, landed)| *alive && !landed)
            .map(|(_, p, _, _)| *p)
            .collect();
        for t in &mut self.targets {
            t.step(dt, &self.bounds, &alive_airborne);
        }
        let breach = self.stats.update(&airborne, struck_ground, &self.rules);
        if let (Some((i, j, distance)), None) = (breach.separation, self.last_breaches.separation) {
            let ((a, pa), (b, pb)) = (airborne_ids[i], airborne_ids[j]);
            tracing::warn!(
                time = self.time,
                "separation breach begins: {a} at ({:.2}, {:.2}, {:.2}) and {b} at ({:.2}, {:.2}, {:.2}) are {distance:.2} m apart",
                pa.x,
                pa.y,
                pa.z,
                pb.x,
                pb.y,
                pb.z
            );
        }
        if let (Some((i, k, clearance)), None) = (breach.obstacle, self.last_breaches.obstacle) {
            let (drone, p) = airborne_ids[i];
            let obstacle = self.rules.obstacles.get(k).map_or("?", |o| o.name.as_str());
            tracing::warn!(
                time = self.time,
                "obstacle breach begins: {drone} at ({:.2}, {:.2}, {:.2}) is {clearance:.2} m from {obstacle}",
                p.x,
                p.y,
                p.z
            );
        }
        self.last_breaches = breach;

        let observers: Vec<Observer<'_>> = fleet
            .iter()
            .map(|(drone, position, alive, landed)| Observer {
                drone,
                position: *position,
                can_see: *alive && !landed,
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
            vehicles: self
                .vehicles
                .iter()
                .map(|v| v.truth(self.time))
                .chain(self.observed.iter().map(|v| v.truth(self.time)))
                .collect(),
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

/// Every vehicle of the world, simulated or observed: (id, world position, alive, landed). A
/// function of the two lists, not of the whole simulation, so the targets and statistics can be
/// stepped while it is borrowed.
fn fleet<'a>(
    vehicles: &'a [SimVehicle],
    observed: &'a [ObservedVehicle],
    now: f64,
) -> Vec<(&'a DroneId, Vec3, bool, bool)> {
    let simulated = vehicles.iter().map(|v| {
        (
            &v.id,
            v.position_enu(),
            v.vehicle.alive(),
            v.vehicle.landed(),
        )
    });
    let observed = observed
        .iter()
        .map(|v| (&v.id, v.position_enu(), v.alive(now), v.landed()));
    simulated.chain(observed).collect()
}

#[cfg(test)]
mod tests;
