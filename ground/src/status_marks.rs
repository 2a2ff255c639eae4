//! The bracketed marks after a drone's action state, the same in the terminal's drone rows
//! and the `swarm` table: a failsafe under way, no neighbour heard, PX4 flying the drone.

use std::fmt::Write;
use tacos_shared::messages::FailsafeStage;
use tacos_shared::px4_mode::Px4Mode;

/// " [failsafe hold]", " [no peer heard]", " [PX4 flies it: Hold]", those that apply, in that
/// order; empty when none does.
pub fn status_marks(
    failsafe: Option<FailsafeStage>,
    peers_silent: bool,
    autopilot_took_over: Option<Px4Mode>,
) -> String {
    let mut marks = String::new();
    match failsafe {
        Some(FailsafeStage::Holding) => marks.push_str(" [failsafe hold]"),
        Some(FailsafeStage::Landing) => marks.push_str(" [failsafe land]"),
        None => {}
    }
    if peers_silent {
        marks.push_str(" [no peer heard]");
    }
    if let Some(mode) = autopilot_took_over {
        let _ = write!(marks, " [PX4 flies it: {mode}]");
    }
    marks
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn marks_name_what_applies_in_order() {
        assert_eq!(status_marks(None, false, None), "");
        assert_eq!(
            status_marks(Some(FailsafeStage::Landing), true, Some(Px4Mode::Hold)),
            " [failsafe land] [no peer heard] [PX4 flies it: Hold]"
        );
        assert_eq!(
            status_marks(Some(FailsafeStage::Holding), false, None),
            " [failsafe hold]"
        );
    }
}
