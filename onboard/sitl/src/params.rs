//! PX4's parameters, the few the stand-in knows: a table with PX4's defaults and types, read and
//! written as PX4's MAVLink parameter protocol does (measured on PX4 SITL):
//! - PARAM_REQUEST_READ by name (param_index -1) or by index, and PARAM_REQUEST_LIST, are
//!   answered with PARAM_VALUE; a name PX4 does not have gets no answer at all.
//! - PARAM_SET is answered with a PARAM_VALUE echo of the value now held. PX4 copies the four
//!   bytes of param_value into the parameter whatever param_type says, so a float sent for an
//!   integer parameter arrives garbled, exactly as on PX4.
//! - An INT32 travels byte for byte in the float field (param_type 6), a float as such (9).
//!
//! Which of them change what the vehicle does is on [`crate::vehicle`]: `COM_OBL_RC_ACT` and
//! `COM_OF_LOSS_T` (the offboard-loss failsafe). The others are held and reported only.
//! Pure.

use mavlink::dialects::common::MavParamType;

/// A parameter's value in its own type.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ParamValue {
    Int(i32),
    Real(f32),
}

impl ParamValue {
    /// PARAM_VALUE's float field and type.
    pub fn to_wire(self) -> (f32, MavParamType) {
        match self {
            ParamValue::Int(v) => (
                f32::from_le_bytes(v.to_le_bytes()),
                MavParamType::MAV_PARAM_TYPE_INT32,
            ),
            ParamValue::Real(v) => (v, MavParamType::MAV_PARAM_TYPE_REAL32),
        }
    }

    /// PARAM_SET's float field, read in this value's type (byte for byte, as PX4 does).
    pub fn with_wire(self, raw: f32) -> ParamValue {
        match self {
            ParamValue::Int(_) => ParamValue::Int(i32::from_le_bytes(raw.to_le_bytes())),
            ParamValue::Real(_) => ParamValue::Real(raw),
        }
    }
}

/// `COM_OBL_RC_ACT`: what PX4 does when offboard setpoints stop (0 Position, 1 Altitude,
/// 2 Manual, 3 Return, 4 Land, 5 Hold, 6 Terminate, 7 Disarm).
pub const COM_OBL_RC_ACT: &str = "COM_OBL_RC_ACT";
/// `COM_OF_LOSS_T`: seconds without offboard setpoints before that action.
pub const COM_OF_LOSS_T: &str = "COM_OF_LOSS_T";

/// The parameters and PX4's defaults (PX4 main), in index order.
const DEFAULTS: [(&str, ParamValue); 8] = [
    (COM_OBL_RC_ACT, ParamValue::Int(0)),
    (COM_OF_LOSS_T, ParamValue::Real(1.0)),
    // Data-link loss action (0 disabled).
    ("NAV_DLL_ACT", ParamValue::Int(0)),
    // RC-loss exceptions (bit 2: offboard).
    ("COM_RCL_EXCEPT", ParamValue::Int(0)),
    // RC-loss action (2 Return).
    ("NAV_RCL_ACT", ParamValue::Int(2)),
    // RC input mode (1 joystick only).
    ("COM_RC_IN_MODE", ParamValue::Int(1)),
    // Geofence breach action (1 warn, 2 hold, 3 return, 5 land).
    ("GF_ACTION", ParamValue::Int(2)),
    // Geofence altitude limit above home, metres (0 off).
    ("GF_MAX_VER_DIST", ParamValue::Real(0.0)),
];

/// What the vehicle does when its offboard setpoints stop (`COM_OBL_RC_ACT`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum OffboardLossAction {
    /// 5 (and any value PX4 does not define).
    Hold,
    /// 4.
    Land,
    /// 3, and 0–2: those are manual modes that need a remote control, which a simulated vehicle
    /// never has (PX4 without RC returns for its default 0).
    Return,
    /// 6 Terminate and 7 Disarm: the motors stop.
    MotorsOff,
}

impl OffboardLossAction {
    pub fn from_param(value: i32) -> Self {
        match value {
            0..=3 => OffboardLossAction::Return,
            4 => OffboardLossAction::Land,
            6 | 7 => OffboardLossAction::MotorsOff,
            _ => OffboardLossAction::Hold,
        }
    }
}

/// The parameter table of one vehicle.
#[derive(Debug, Clone, PartialEq)]
pub struct Px4Params {
    entries: Vec<(&'static str, ParamValue)>,
}

impl Default for Px4Params {
    fn default() -> Self {
        Px4Params {
            entries: DEFAULTS.to_vec(),
        }
    }
}

impl Px4Params {
    pub fn len(&self) -> usize {
        self.entries.len()
    }

    pub fn is_empty(&self) -> bool {
        self.entries.is_empty()
    }

    /// The index of parameter `name`, if PX4 has it.
    pub fn index_of(&self, name: &str) -> Option<usize> {
        self.entries.iter().position(|(n, _)| *n == name)
    }

    /// Parameter `index`: its name and value.
    pub fn get(&self, index: usize) -> Option<(&'static str, ParamValue)> {
        self.entries.get(index).copied()
    }

    pub fn value(&self, name: &str) -> Option<ParamValue> {
        self.index_of(name)
            .and_then(|i| self.get(i))
            .map(|(_, v)| v)
    }

    /// Sets parameter `index` from PARAM_SET's float field; returns the value now held.
    pub fn set_from_wire(&mut self, index: usize, raw: f32) -> Option<ParamValue> {
        let (_, value) = self.entries.get_mut(index)?;
        *value = value.with_wire(raw);
        Some(*value)
    }

    /// Sets parameter `name` (a test's or a scenario's set-up); false when there is none or
    /// the type differs.
    pub fn set(&mut self, name: &str, value: ParamValue) -> bool {
        let Some((_, held)) = self.entries.iter_mut().find(|(n, _)| *n == name) else {
            return false;
        };
        if std::mem::discriminant(held) != std::mem::discriminant(&value) {
            return false;
        }
        *held = value;
        true
    }

    /// `COM_OBL_RC_ACT`.
    pub fn offboard_loss_action(&self) -> OffboardLossAction {
        match self.value(COM_OBL_RC_ACT) {
            Some(ParamValue::Int(v)) => OffboardLossAction::from_param(v),
            _ => OffboardLossAction::Hold,
        }
    }

    /// `COM_OF_LOSS_T` in seconds (PX4's range, 0 to 60 s; a non-finite value counts as its
    /// default, 1 s).
    pub fn offboard_loss_timeout(&self) -> f64 {
        match self.value(COM_OF_LOSS_T) {
            Some(ParamValue::Real(t)) if t.is_finite() => f64::from(t).clamp(0.0, 60.0),
            _ => crate::vehicle::OFFBOARD_LOSS_TIMEOUT,
        }
    }
}

/// A parameter name as PARAM_* carry it (NUL-padded, at most 16 bytes).
pub fn name_of(id: &[u8]) -> String {
    let end = id.iter().position(|b| *b == 0).unwrap_or(id.len());
    String::from_utf8_lossy(id.get(..end).unwrap_or_default()).into_owned()
}

/// A name as PARAM_VALUE's param_id.
pub fn param_id(name: &str) -> mavlink::types::CharArray<16> {
    let mut id = [0u8; 16];
    for (slot, byte) in id.iter_mut().zip(name.bytes()) {
        *slot = byte;
    }
    mavlink::types::CharArray::new(id)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn integers_travel_byte_for_byte_and_a_float_for_an_integer_is_garbled() {
        // Measured: PX4 SITL sends COM_OBL_RC_ACT = 5 as param_value 7.0e-45, type 6.
        let (raw, kind) = ParamValue::Int(5).to_wire();
        assert_eq!(kind, MavParamType::MAV_PARAM_TYPE_INT32);
        assert_eq!(raw.to_bits(), 5);
        let mut p = Px4Params::default();
        let i = p.index_of(COM_OBL_RC_ACT).expect("known");
        assert_eq!(p.set_from_wire(i, raw), Some(ParamValue::Int(5)));
        assert_eq!(p.offboard_loss_action(), OffboardLossAction::Hold);
        // 4.0 as a float is 0x40800000 as an integer.
        assert_eq!(p.set_from_wire(i, 4.0), Some(ParamValue::Int(0x4080_0000)));
        let t = p.index_of(COM_OF_LOSS_T).expect("known");
        assert_eq!(p.set_from_wire(t, 2.5), Some(ParamValue::Real(2.5)));
        assert_eq!(p.offboard_loss_timeout(), 2.5);
    }

    #[test]
    fn px4s_defaults_and_unknown_names() {
        let p = Px4Params::default();
        assert_eq!(p.len(), 8);
        assert_eq!(p.value("COM_OBL_RC_ACT"), Some(ParamValue::Int(0)));
        assert_eq!(p.value("GF_MAX_VER_DIST"), Some(ParamValue::Real(0.0)));
        assert_eq!(p.value("NO_SUCH_PARAM"), None);
        assert_eq!(p.offboard_loss_action(), OffboardLossAction::Return);
        assert_eq!(p.offboard_loss_timeout(), 1.0);
        assert_eq!(name_of(&param_id("NAV_DLL_ACT")[..]), "NAV_DLL_ACT");
        assert_eq!(name_of(b"GF_MAX_VER_DIST_"), "GF_MAX_VER_DIST_");
    }

    #[test]
    fn the_offboard_loss_actions() {
        use OffboardLossAction as A;
        let actions: Vec<_> = (0..=8).map(A::from_param).collect();
        assert_eq!(
            actions,
            vec![
                A::Return,
                A::Return,
                A::Return,
                A::Return,
                A::Land,
                A::Hold,
                A::MotorsOff,
                A::MotorsOff,
                A::Hold
            ]
        );
        let mut p = Px4Params::default();
        assert!(p.set(COM_OF_LOSS_T, ParamValue::Real(f32::NAN)));
        assert_eq!(p.offboard_loss_timeout(), 1.0);
        assert!(
            !p.set(COM_OF_LOSS_T, ParamValue::Int(3)),
            "the type is fixed"
        );
        assert!(!p.set("NO_SUCH_PARAM", ParamValue::Int(3)));
    }
}
