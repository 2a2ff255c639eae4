//! The swarm as a text table (for `tacos-ground swarm` and the demo's log).

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
                let failsafe = s
                    .failsafe
                    .map(|f| format!(" [failsafe {f:?}]"))
                    .unwrap_or_default()
                    + &s.autopilot_took_over
                        .map(|m| format!(" [PX4 flies it: {m}]"))
                        .unwrap_or_default();
                (
                    format!(
                        "({:>7.1}, {:>7.1}, {:>5.1})",
                        s.position.x, s.position.y, s.position.z
                    ),
                    format!("{:.1}", s.velocity.norm()),
                    action,
                    state + &failsafe,
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
        state.truncate(40);
        let _ = writeln!(
            out,
            "{:<10} {:<11} {:>26} {:>6} {:<30} {:<22} {:>8}",
            entry.id, mode, position, speed, action, state, link
        );
    }
    out
}
