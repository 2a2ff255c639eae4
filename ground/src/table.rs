//! The swarm as a text table (for `tacos-ground swarm` and the demo's log).

use crate::status_marks::status_marks;
use crate::swarm::SwarmView;
use std::fmt::Write;
use std::time::Instant;
use tacos_shared::messages::ActionState;

/// Renders one row per known drone.
pub fn render(view: &SwarmView, now: Instant) -> String {
    let mut out = String::new();
    let _ = writeln!(
        out,
        "{:<10} {:<11} {:>26} {:>6} {:<30} {:<22} {:>8}",
        "DRONE", "MODE", "POSITION (x, y, z) m", "SPEED", "ACTION", "STATE", "LINK"
    );
    for entry in view.drones() {
        let mode = entry.effective_mode(now);
        let (position, speed, action, state) = match &entry.status {
            Some(s) => {
                let (action, state) = match &s.action {
                    Some(p) => (
                        format!("#{} {}", p.seq % 100_000, p.action),
                        match &p.state {
                            ActionState::Running { progress } => {
                                format!("running {:>3.0}%", progress * 100.0)
                            }
                            ActionState::Done => "done".to_owned(),
                            ActionState::Failed(why) => format!("failed: {why}"),
                        },
                    ),
                    None => ("-".to_owned(), "-".to_owned()),
                };
                let marks = status_marks(s.failsafe, s.peers_silent, s.autopilot_took_over);
                (
                    format!(
                        "({:>7.1}, {:>7.1}, {:>5.1})",
                        s.position.x, s.position.y, s.position.z
                    ),
                    format!("{:.1}", s.velocity.norm()),
                    action,
                    state + &marks,
                )
            }
            None => ("-".into(), "-".into(), "-".into(), "-".into()),
        };
        let link = match (entry.alive, entry.link_age(now)) {
            (false, _) => "gone".to_owned(),
            (true, Some(age)) => format!("{:.0} ms", age * 1000.0),
            (true, None) => "no data".to_owned(),
        };
        let mut state = state;
        // The state holds a drone's own words (a failure's reason): cut on a character.
        state.truncate(state.floor_char_boundary(40));
        let _ = writeln!(
            out,
            "{:<10} {:<11} {:>26} {:>6} {:<30} {:<22} {:>8}",
            entry.id, mode, position, speed, action, state, link
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::swarm::test_status;
    use tacos_shared::DroneMode;
    use tacos_shared::action::Action;
    use tacos_shared::messages::{ActionProgress, FailsafeStage, FailureReason};
    use tacos_shared::px4_mode::Px4Mode;

    /// A long reason in the drone's own (non-ASCII) words is cut on a character, and the marks
    /// are the terminal's.
    #[test]
    fn a_row_cuts_a_long_reason_on_a_character_and_shows_the_marks() {
        let now = Instant::now();
        let mut view = SwarmView::default();
        let mut alfa = test_status("alfa", DroneMode::Flying);
        alfa.action = Some(ActionProgress {
            seq: 7,
            task_id: None,
            action: Action::Hold,
            state: ActionState::Failed(FailureReason::Rejected("ééééééééééééééééééééé".into())),
        });
        view.apply_status(alfa, now);
        let mut bravo = test_status("bravo", DroneMode::Flying);
        bravo.failsafe = Some(FailsafeStage::Holding);
        bravo.autopilot_took_over = Some(Px4Mode::Hold);
        view.apply_status(bravo, now);

        let table = render(&view, now);
        let alfa_row = table
            .lines()
            .find(|l| l.starts_with("alfa"))
            .unwrap_or_default();
        assert!(alfa_row.contains("failed: "), "{table}");
        let bravo_row = table
            .lines()
            .find(|l| l.starts_with("bravo"))
            .unwrap_or_default();
        assert!(
            bravo_row.contains(" - [failsafe hold] [PX4 flies it: Hold]"),
            "{table}"
        );
    }
}
