//! PX4's custom-mode encoding in HEARTBEAT.custom_mode: main mode in bits 16..24, sub mode in
//! bits 24..32 (`px4_custom_mode.h`). Pure numbers, shared by the writer and the simulator.

pub const MAIN_MANUAL: u8 = 1;
pub const MAIN_ALTCTL: u8 = 2;
pub const MAIN_POSCTL: u8 = 3;
pub const MAIN_AUTO: u8 = 4;
pub const MAIN_OFFBOARD: u8 = 6;

pub const AUTO_READY: u8 = 1;
pub const AUTO_TAKEOFF: u8 = 2;
/// "Hold" in QGroundControl.
pub const AUTO_LOITER: u8 = 3;
pub const AUTO_MISSION: u8 = 4;
pub const AUTO_RTL: u8 = 5;
pub const AUTO_LAND: u8 = 6;

/// MAV_MODE_FLAG_CUSTOM_MODE_ENABLED: base_mode bit that says custom_mode is meaningful.
pub const BASE_MODE_CUSTOM_ENABLED: u8 = 1;
/// MAV_MODE_FLAG_SAFETY_ARMED.
pub const BASE_MODE_ARMED: u8 = 128;

/// The flight modes TACOS cares about.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub enum Px4Mode {
    Manual,
    Position,
    Takeoff,
    Hold,
    Land,
    Offboard,
    Other { main: u8, sub: u8 },
}

impl Px4Mode {
    pub fn custom_mode(self) -> u32 {
        let (main, sub) = self.main_sub();
        (u32::from(main) << 16) | (u32::from(sub) << 24)
    }

    /// The main and sub mode, as DO_SET_MODE's second and third parameters carry them.
    pub fn main_sub(self) -> (u8, u8) {
        match self {
            Px4Mode::Manual => (MAIN_MANUAL, 0),
            Px4Mode::Position => (MAIN_POSCTL, 0),
            Px4Mode::Takeoff => (MAIN_AUTO, AUTO_TAKEOFF),
            Px4Mode::Hold => (MAIN_AUTO, AUTO_LOITER),
            Px4Mode::Land => (MAIN_AUTO, AUTO_LAND),
            Px4Mode::Offboard => (MAIN_OFFBOARD, 0),
            Px4Mode::Other { main, sub } => (main, sub),
        }
    }

    pub fn from_custom_mode(custom_mode: u32) -> Px4Mode {
        let main = ((custom_mode >> 16) & 0xff) as u8;
        let sub = ((custom_mode >> 24) & 0xff) as u8;
        match (main, sub) {
            (MAIN_MANUAL, _) => Px4Mode::Manual,
            (MAIN_POSCTL, _) => Px4Mode::Position,
            (MAIN_AUTO, AUTO_TAKEOFF) => Px4Mode::Takeoff,
            (MAIN_AUTO, AUTO_LOITER) => Px4Mode::Hold,
            (MAIN_AUTO, AUTO_LAND) => Px4Mode::Land,
            (MAIN_OFFBOARD, _) => Px4Mode::Offboard,
            (main, sub) => Px4Mode::Other { main, sub },
        }
    }

    /// A compact code for shared-memory payloads (see `ipc::VehicleState`).
    pub fn code(self) -> u32 {
        self.custom_mode()
    }
}

/// The mode's name as QGroundControl shows it ("Return", not "AUTO.RTL").
impl std::fmt::Display for Px4Mode {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let name = match *self {
            Px4Mode::Manual => "Manual",
            Px4Mode::Position => "Position",
            Px4Mode::Takeoff => "Takeoff",
            Px4Mode::Hold => "Hold",
            Px4Mode::Land => "Land",
            Px4Mode::Offboard => "Offboard",
            Px4Mode::Other {
                main: MAIN_ALTCTL, ..
            } => "Altitude",
            Px4Mode::Other {
                main: MAIN_AUTO,
                sub: AUTO_RTL,
            } => "Return",
            Px4Mode::Other {
                main: MAIN_AUTO,
                sub: AUTO_MISSION,
            } => "Mission",
            Px4Mode::Other {
                main: MAIN_AUTO,
                sub: AUTO_READY,
            } => "Ready",
            Px4Mode::Other { main, sub } => return write!(f, "mode {main}.{sub}"),
        };
        f.write_str(name)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_encodings() {
        // Values seen in PX4 heartbeats: offboard = 6 << 16, hold = 4 << 16 | 3 << 24.
        assert_eq!(Px4Mode::Offboard.custom_mode(), 393_216);
        assert_eq!(Px4Mode::Hold.custom_mode(), 50_593_792);
        for m in [
            Px4Mode::Manual,
            Px4Mode::Position,
            Px4Mode::Takeoff,
            Px4Mode::Hold,
            Px4Mode::Land,
            Px4Mode::Offboard,
        ] {
            assert_eq!(Px4Mode::from_custom_mode(m.custom_mode()), m);
        }
    }

    #[test]
    fn modes_are_named_as_a_ground_station_names_them() {
        let rtl = Px4Mode::from_custom_mode(
            Px4Mode::Other {
                main: MAIN_AUTO,
                sub: AUTO_RTL,
            }
            .custom_mode(),
        );
        assert_eq!(rtl.to_string(), "Return");
        assert_eq!(Px4Mode::Hold.to_string(), "Hold");
        assert_eq!(Px4Mode::Other { main: 9, sub: 1 }.to_string(), "mode 9.1");
    }
}
