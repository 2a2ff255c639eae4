//! The one wire codec: a version byte, then bincode 2 (serde) in its standard configuration.
//!
//! Everything on zenoh goes through [`encode`] / [`decode`], so the format can be changed in one
//! place. Decoding is strict: an unknown version, a short buffer and trailing bytes are errors.

use serde::Serialize;
use serde::de::DeserializeOwned;

/// The current wire version. Bump when any message changes shape.
pub const WIRE_VERSION: u8 = 5;

/// Upper bound on what one message may allocate while decoding, so garbage cannot exhaust memory.
pub const MAX_MESSAGE_BYTES: usize = 1 << 20;

fn config() -> impl bincode::config::Config {
    bincode::config::standard().with_limit::<MAX_MESSAGE_BYTES>()
}

#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum CodecError {
    #[error("empty message")]
    Empty,
    #[error("unknown wire version {found} (this build speaks {WIRE_VERSION})")]
    UnknownVersion { found: u8 },
    #[error("message truncated")]
    Truncated,
    #[error("{0} trailing byte(s) after the message")]
    TrailingBytes(usize),
    #[error("malformed message: {0}")]
    Malformed(String),
    #[error("could not encode: {0}")]
    Encode(String),
}

/// Encodes `value` behind the version byte.
pub fn encode<T: Serialize>(value: &T) -> Result<Vec<u8>, CodecError> {
    let mut out = vec![WIRE_VERSION];
    bincode::serde::encode_into_std_write(value, &mut out, config())
        .map_err(|e| CodecError::Encode(e.to_string()))?;
    Ok(out)
}

/// Decodes a whole message; rejects unknown versions, truncation and trailing bytes.
pub fn decode<T: DeserializeOwned>(bytes: &[u8]) -> Result<T, CodecError> {
    let (&version, body) = bytes.split_first().ok_or(CodecError::Empty)?;
    if version != WIRE_VERSION {
        return Err(CodecError::UnknownVersion { found: version });
    }
    let (value, used) = bincode::serde::decode_from_slice(body, config()).map_err(|e| match e {
        bincode::error::DecodeError::UnexpectedEnd { .. } => CodecError::Truncated,
        other => CodecError::Malformed(other.to_string()),
    })?;
    if used != body.len() {
        return Err(CodecError::TrailingBytes(body.len() - used));
    }
    Ok(value)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::action::{Action, ActionCommand};
    use crate::geometry::Vec3;
    use crate::ids::DroneId;
    use crate::messages::*;
    use crate::mode::DroneMode;
    use crate::px4_mode::Px4Mode;
    use proptest::prelude::*;

    fn finite() -> impl Strategy<Value = f64> {
        -1.0e6..1.0e6f64
    }

    fn vec3() -> impl Strategy<Value = Vec3> {
        (finite(), finite(), finite()).prop_map(|(x, y, z)| Vec3::new(x, y, z))
    }

    fn action() -> impl Strategy<Value = Action> {
        prop_oneof![
            Just(Action::ArmTakeoff),
            vec3().prop_map(|target| Action::Goto { target }),
            "[a-z_]{1,20}".prop_map(|target| Action::StartTracking { target }),
            Just(Action::StopTracking),
            Just(Action::Land),
            Just(Action::Hold),
        ]
    }

    fn command() -> impl Strategy<Value = ActionCommand> {
        (
            any::<u64>(),
            proptest::option::of("[A-Za-z0-9]{0,8}"),
            action(),
        )
            .prop_map(|(seq, task_id, action)| ActionCommand {
                ground: seq / 3,
                seq,
                sent_at: seq as f64 / 7.0,
                task_id,
                action,
            })
    }

    fn status() -> impl Strategy<Value = DroneStatus> {
        (
            any::<u64>(),
            vec3(),
            vec3(),
            any::<bool>(),
            proptest::option::of(command()),
        )
            .prop_map(|(counter, position, velocity, armed, cmd)| DroneStatus {
                drone: DroneId::new("alfa").expect("valid id"),
                counter,
                mode: DroneMode::Flying,
                armed,
                position,
                velocity,
                autopilot_link: true,
                action: cmd.as_ref().map(|c| ActionProgress {
                    state: ActionState::Failed(FailureReason::Unreachable("x".into())),
                    ..ActionProgress::started(c)
                }),
                failsafe: Some(FailsafeStage::Holding),
                peers_silent: false,
                malformed_actions: 3,
                ground: Some(counter / 2),
                refused: cmd.map(|c| ActionRefused {
                    seq: c.seq,
                    why: RefusedBecause::Late {
                        late_s: 2.5,
                        bound_s: 2.0,
                    },
                }),
                autopilot_took_over: (counter % 2 == 0).then_some(Px4Mode::Hold),
            })
    }

    proptest! {
        #[test]
        fn commands_round_trip(cmd in command()) {
            let bytes = encode(&cmd).expect("encodes");
            prop_assert_eq!(decode::<ActionCommand>(&bytes), Ok(cmd));
        }

        #[test]
        fn statuses_round_trip(st in status()) {
            let bytes = encode(&st).expect("encodes");
            prop_assert_eq!(decode::<DroneStatus>(&bytes), Ok(st));
        }

        #[test]
        fn every_strict_prefix_is_rejected(cmd in command()) {
            let bytes = encode(&cmd).expect("encodes");
            for cut in 0..bytes.len() {
                prop_assert!(decode::<ActionCommand>(&bytes[..cut]).is_err(), "prefix {} accepted", cut);
            }
        }

        #[test]
        fn garbage_never_panics(bytes in proptest::collection::vec(any::<u8>(), 0..256)) {
            let _ = decode::<ActionCommand>(&bytes);
            let _ = decode::<DroneStatus>(&bytes);
        }
    }

    #[test]
    fn typed_errors() {
        let bytes = encode(&ActionCommand {
            ground: 1,
            seq: 7,
            sent_at: 1.0,
            task_id: None,
            action: Action::Land,
        })
        .expect("encodes");
        assert_eq!(decode::<ActionCommand>(&[]), Err(CodecError::Empty));
        let mut wrong_version = bytes.clone();
        wrong_version[0] = 9;
        assert_eq!(
            decode::<ActionCommand>(&wrong_version),
            Err(CodecError::UnknownVersion { found: 9 })
        );
        assert_eq!(
            decode::<ActionCommand>(&bytes[..bytes.len() - 1]),
            Err(CodecError::Truncated)
        );
        let mut trailing = bytes.clone();
        trailing.extend_from_slice(&[0, 0]);
        assert_eq!(
            decode::<ActionCommand>(&trailing),
            Err(CodecError::TrailingBytes(2))
        );
        // An enum discriminant that does not exist (after ground, seq and an 8-byte sent_at).
        assert!(matches!(
            decode::<ActionCommand>(&[WIRE_VERSION, 1, 0, 0, 0, 0, 0, 0, 0, 0, 0, 99]),
            Err(CodecError::Malformed(_))
        ));
    }
}
