//! Vehicles the world does not simulate but observes: real PX4 SITL instances, each read on its
//! own GCS link (HEARTBEAT, LOCAL_POSITION_NED, EXTENDED_SYS_STATE), independently of the
//! writer that flies it. With `--observe-px4-gcs-port` the simulator's truth, detections and
//! breach checks come from what these vehicles report. Pure: the time is passed in.

use mavlink::dialects::common::{MavAutopilot, MavLandedState, MavMessage, MavModeFlag};
use tacos_shared::frames::{Home, ned_vector_to_enu};
use tacos_shared::messages::VehicleTruth;
use tacos_shared::{DroneId, Vec3};

/// No heartbeat for this long: the vehicle is taken to be dead (its PX4 stopped).
pub const SILENCE_S: f64 = 3.0;
/// Without EXTENDED_SYS_STATE, a vehicle this low above its home counts as landed.
const LANDED_ALTITUDE_M: f64 = 0.3;
/// A vehicle whose reported height above its home is within this, and whose vertical speed is
/// within [`ON_FLOOR_VZ`], is on the floor: it counts as landed before PX4's land detector says
/// so (that takes about 3.5 s on the floor: ground contact, maybe landed, landed), as
/// tacos-sitl's own vehicles count from touchdown. Measured on the lab map: the separation
/// breaches of PX4 SIH runs all began in that wait, with the vehicles reported 0.07–0.14 m from
/// the floor while their estimates wandered sideways.
const ON_FLOOR_HEIGHT_M: f64 = 0.15;
const ON_FLOOR_VZ: f64 = 0.2;

/// The heartbeat an observer sends on a vehicle's GCS link: a ground station's.
pub fn gcs_heartbeat() -> MavMessage {
    use mavlink::dialects::common::{HEARTBEAT_DATA, MavState, MavType};
    MavMessage::HEARTBEAT(HEARTBEAT_DATA {
        custom_mode: 0,
        mavtype: MavType::MAV_TYPE_GCS,
        autopilot: MavAutopilot::MAV_AUTOPILOT_INVALID,
        base_mode: MavModeFlag::empty(),
        system_status: MavState::MAV_STATE_ACTIVE,
        mavlink_version: 3,
    })
}

#[derive(Debug, Clone)]
pub struct ObservedVehicle {
    pub id: DroneId,
    pub home: Home,
    /// The PX4 instance's MAV_SYS_ID: only its messages count.
    pub sysid: u8,
    last_heartbeat: Option<f64>,
    armed: bool,
    custom_mode: u32,
    landed_state: Option<MavLandedState>,
    /// Local NED position and velocity.
    ned: Option<(Vec3, Vec3)>,
}

impl ObservedVehicle {
    pub fn new(id: DroneId, home: Home, sysid: u8) -> Self {
        ObservedVehicle {
            id,
            home,
            sysid,
            last_heartbeat: None,
            armed: false,
            custom_mode: 0,
            landed_state: None,
            ned: None,
        }
    }

    /// One message heard on the vehicle's GCS link at `now` (sim seconds).
    pub fn on_message(&mut self, sysid: u8, compid: u8, msg: &MavMessage, now: f64) {
        if sysid != self.sysid || compid != 1 {
            return;
        }
        match msg {
            MavMessage::HEARTBEAT(hb) if hb.autopilot != MavAutopilot::MAV_AUTOPILOT_INVALID => {
                self.last_heartbeat = Some(now);
                self.armed = hb
                    .base_mode
                    .contains(MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED);
                self.custom_mode = hb.custom_mode;
            }
            MavMessage::LOCAL_POSITION_NED(p) => {
                let pos = Vec3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                let vel = Vec3::new(f64::from(p.vx), f64::from(p.vy), f64::from(p.vz));
                if pos.iter().chain(vel.iter()).all(|c| c.is_finite()) {
                    self.ned = Some((pos, vel));
                }
            }
            MavMessage::EXTENDED_SYS_STATE(s) => self.landed_state = Some(s.landed_state),
            _ => {}
        }
    }

    /// Heard from within [`SILENCE_S`].
    pub fn alive(&self, now: f64) -> bool {
        self.last_heartbeat.is_some_and(|t| now - t <= SILENCE_S)
    }

    /// World ENU position (the home until the first position).
    pub fn position_enu(&self) -> Vec3 {
        self.ned
            .map_or(self.home.enu, |(p, _)| self.home.ned_to_enu(&p))
    }

    pub fn velocity_enu(&self) -> Vec3 {
        self.ned
            .map_or(Vec3::zeros(), |(_, v)| ned_vector_to_enu(&v))
    }

    pub fn landed(&self) -> bool {
        match self.landed_state {
            Some(MavLandedState::MAV_LANDED_STATE_ON_GROUND) => true,
            Some(MavLandedState::MAV_LANDED_STATE_UNDEFINED) | None => {
                self.position_enu().z - self.home.enu.z < LANDED_ALTITUDE_M
            }
            Some(_) => self.on_the_floor(),
        }
    }

    /// Still on the floor by what it reports, whatever PX4's land detector says yet.
    fn on_the_floor(&self) -> bool {
        (self.position_enu().z - self.home.enu.z).abs() <= ON_FLOOR_HEIGHT_M
            && self.velocity_enu().z.abs() <= ON_FLOOR_VZ
    }

    pub fn truth(&self, now: f64) -> VehicleTruth {
        VehicleTruth {
            drone: self.id.clone(),
            position: self.position_enu(),
            velocity: self.velocity_enu(),
            armed: self.armed,
            custom_mode: self.custom_mode,
            alive: self.alive(now),
            link_down: false,
            landed: self.landed(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use mavlink::dialects::common::{
        EXTENDED_SYS_STATE_DATA, HEARTBEAT_DATA, LOCAL_POSITION_NED_DATA, MavState, MavType,
        MavVtolState,
    };

    fn heartbeat(armed: bool) -> MavMessage {
        let mut base = MavModeFlag::MAV_MODE_FLAG_CUSTOM_MODE_ENABLED;
        if armed {
            base |= MavModeFlag::MAV_MODE_FLAG_SAFETY_ARMED;
        }
        MavMessage::HEARTBEAT(HEARTBEAT_DATA {
            custom_mode: 0x0006_0000,
            mavtype: MavType::MAV_TYPE_QUADROTOR,
            autopilot: MavAutopilot::MAV_AUTOPILOT_PX4,
            base_mode: base,
            system_status: MavState::MAV_STATE_ACTIVE,
            mavlink_version: 3,
        })
    }

    #[test]
    fn what_the_vehicle_reports_is_its_truth_in_world_enu() {
        let id = DroneId::new("alfa").expect("id");
        let mut v = ObservedVehicle::new(id, Home::new(Vec3::new(100.0, 50.0, 1.0)), 3);
        assert!(!v.alive(0.0) && v.landed());
        v.on_message(3, 1, &heartbeat(true), 1.0);
        // Another vehicle's position on the same port is not this one's.
        let pos = MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
            time_boot_ms: 0,
            x: 10.0,
            y: 5.0,
            z: -8.0,
            vx: 0.0,
            vy: 0.0,
            vz: -1.0,
        });
        v.on_message(4, 1, &pos, 1.0);
        assert_eq!(v.position_enu(), Vec3::new(100.0, 50.0, 1.0));
        v.on_message(3, 1, &pos, 1.1);
        v.on_message(
            3,
            1,
            &MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
                vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
                landed_state: MavLandedState::MAV_LANDED_STATE_IN_AIR,
            }),
            1.1,
        );
        let t = v.truth(1.2);
        assert_eq!(t.position, Vec3::new(105.0, 60.0, 9.0));
        assert_eq!(t.velocity, Vec3::new(0.0, 0.0, 1.0));
        assert!(t.alive && t.armed && !t.landed && !t.link_down);
        assert_eq!(t.custom_mode, 0x0006_0000);
        assert!(!v.alive(1.0 + SILENCE_S + 0.1), "a silent PX4 is dead");
    }

    #[test]
    fn a_vehicle_resting_on_the_floor_counts_as_landed_before_px4_says_so() {
        let id = DroneId::new("alfa").expect("id");
        let mut v = ObservedVehicle::new(id, Home::new(Vec3::new(0.0, 0.0, 0.0)), 1);
        let in_air = MavMessage::EXTENDED_SYS_STATE(EXTENDED_SYS_STATE_DATA {
            vtol_state: MavVtolState::MAV_VTOL_STATE_UNDEFINED,
            landed_state: MavLandedState::MAV_LANDED_STATE_IN_AIR,
        });
        let at = |z: f32, vz: f32| {
            MavMessage::LOCAL_POSITION_NED(LOCAL_POSITION_NED_DATA {
                time_boot_ms: 0,
                x: 0.3,
                y: -0.2,
                z: -z,
                vx: 0.0,
                vy: 0.0,
                vz: -vz,
            })
        };
        v.on_message(1, 1, &heartbeat(true), 0.0);
        v.on_message(1, 1, &in_air, 0.0);
        // Hovering low, or sinking onto the floor: in the air.
        v.on_message(1, 1, &at(0.3, 0.0), 0.1);
        assert!(!v.landed());
        v.on_message(1, 1, &at(0.1, -0.8), 0.2);
        assert!(!v.landed());
        // Down, with the estimate a little off the floor either way: landed.
        v.on_message(1, 1, &at(0.12, 0.05), 0.3);
        assert!(v.landed());
        v.on_message(1, 1, &at(-0.1, 0.0), 0.4);
        assert!(v.landed());
        // Lifting off again.
        v.on_message(1, 1, &at(0.1, 0.6), 0.5);
        assert!(!v.landed());
    }
}
