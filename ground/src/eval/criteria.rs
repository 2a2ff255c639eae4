//! The success criteria and the per-run figures, as pure functions of what a run observed: the
//! simulator's truth and events (gathered by `run`) and the mission log.

use super::task::SuccessSpec;
use crate::mission::log::{Line, Record, SentCheck};
use crate::safety::SafetyGate;

/// What a run saw, as the criteria need it.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Observed {
    /// The target to find was detected at its hiding landmark (by this drone).
    pub detected_by: Option<String>,
    /// Every drone was airborne at take-off altitude at some point.
    pub all_airborne: bool,
    pub separation_breaches: u64,
    pub obstacle_breaches: u64,
    /// Actions sent that the safety gate, run again on what it saw, refuses (see
    /// [`unchecked_sends`]).
    pub unchecked_sent: Vec<String>,
    /// Seconds from the first pilot line to the moment the goal was reached, if it was.
    pub goal_at_s: Option<f64>,
}

#[derive(Debug, Clone, PartialEq)]
pub enum Verdict {
    Success,
    Failure(String),
}

impl Verdict {
    pub fn is_success(&self) -> bool {
        matches!(self, Verdict::Success)
    }
}

/// True when `spec`'s goal (not the safety conditions) has been reached.
pub fn goal_reached(spec: &SuccessSpec, seen: &Observed) -> bool {
    (spec.detected.is_none() || seen.detected_by.is_some())
        && (!spec.all_airborne || seen.all_airborne)
}

/// True when the run can no longer succeed whatever happens next (a breach is for good).
pub fn failed_for_good(seen: &Observed) -> bool {
    seen.separation_breaches > 0 || seen.obstacle_breaches > 0
}

/// The verdict on a finished run: the goal reached within the time limit, no separation or
/// obstacle breach, and nothing sent that the safety gate refuses.
pub fn judge(spec: &SuccessSpec, seen: &Observed, time_limit_s: f64) -> Verdict {
    let mut why = Vec::new();
    if seen.separation_breaches > 0 || seen.obstacle_breaches > 0 {
        why.push(format!(
            "collision: {} separation and {} obstacle breach ticks",
            seen.separation_breaches, seen.obstacle_breaches
        ));
    }
    if !seen.unchecked_sent.is_empty() {
        why.push(format!(
            "sent past the safety gate: {}",
            seen.unchecked_sent.join("; ")
        ));
    }
    match seen.goal_at_s {
        Some(t) if goal_reached(spec, seen) && t <= time_limit_s => {}
        Some(t) if goal_reached(spec, seen) => why.push(format!(
            "goal reached after {t:.0} s, over the {time_limit_s:.0} s limit"
        )),
        _ => why.push(match (&spec.detected, spec.all_airborne) {
            (Some(target), _) => format!("{target} not found"),
            (None, _) => "not every drone took off".to_owned(),
        }),
    }
    if why.is_empty() {
        Verdict::Success
    } else {
        Verdict::Failure(why.join("; "))
    }
}

/// A run's figures, read from its mission log.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LogFigures {
    /// Supervisor (or monolithic) cycles: the paper's L for this run.
    pub cycles: u32,
    /// Model requests, repair attempts included.
    pub model_calls: u32,
    /// Replies received (the latency is averaged over these).
    pub replies: u32,
    pub latency_ms_total: u64,
    pub prompt_tokens: u64,
    pub completion_tokens: u64,
    pub gate_rejections: u32,
    pub actions_sent: u32,
}

/// Counts cycles, calls, latency and tokens.
pub fn log_figures(lines: &[Line]) -> LogFigures {
    let mut f = LogFigures::default();
    for line in lines {
        match &line.record {
            Record::SupervisorCycle { .. } => f.cycles += 1,
            Record::LlmRequest { .. } => f.model_calls += 1,
            Record::LlmReply {
                latency_ms,
                prompt_tokens,
                completion_tokens,
                ..
            } => {
                f.replies += 1;
                f.latency_ms_total += latency_ms;
                f.prompt_tokens += u64::from(*prompt_tokens);
                f.completion_tokens += u64::from(*completion_tokens);
            }
            Record::GateRejected { .. } => f.gate_rejections += 1,
            Record::ActionSent { .. } => f.actions_sent += 1,
            _ => {}
        }
    }
    f
}

/// Every action in the log that the safety gate does not pass when run again on what it saw of
/// the drone (the state logged with the send), or that was sent without that record: the audit
/// of the invariant that nothing reaches a drone around the gate, read from the log rather
/// than trusted. Each entry names the send and the gate's reason.
pub fn unchecked_sends(lines: &[Line], gate: &SafetyGate) -> Vec<String> {
    lines
        .iter()
        .filter_map(|line| match &line.record {
            Record::ActionSent {
                drone,
                seq,
                action,
                checked,
                ..
            } => {
                let why = match checked {
                    None => "no record of the gate's check".to_owned(),
                    Some(SentCheck { action: typed, .. }) if typed.to_string() != *action => {
                        format!("logged as {action} but checked as {typed}")
                    }
                    Some(SentCheck { action, seen }) => {
                        gate.recheck(drone, *seen, action).err()?.to_string()
                    }
                };
                Some(format!(
                    "#{seq} {action} to {drone} at {:.1} s: {why}",
                    line.t
                ))
            }
            _ => None,
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn line(t: f64, record: Record) -> Line {
        Line { t, record }
    }

    fn reply(latency_ms: u64) -> Record {
        Record::LlmReply {
            layer: "supervisor".into(),
            attempt: 1,
            content: "{}".into(),
            reasoning: None,
            latency_ms,
            prompt_tokens: 100,
            completion_tokens: 10,
        }
    }

    fn cycle(actions: &[&str]) -> Record {
        Record::SupervisorCycle {
            plan_cycle: 1,
            actions: actions.iter().map(|a| a.to_string()).collect(),
            plan_complete: false,
        }
    }

    fn find() -> SuccessSpec {
        SuccessSpec {
            detected: Some("suspect".into()),
            all_airborne: false,
        }
    }

    fn found_at(t: f64) -> Observed {
        Observed {
            detected_by: Some("bravo".into()),
            goal_at_s: Some(t),
            ..Observed::default()
        }
    }

    #[test]
    fn a_clean_detection_in_time_succeeds() {
        assert_eq!(judge(&find(), &found_at(80.0), 600.0), Verdict::Success);
    }

    #[test]
    fn each_criterion_alone_fails_a_run() {
        let spec = find();
        let not_found = Observed::default();
        assert!(
            matches!(judge(&spec, &not_found, 600.0), Verdict::Failure(w) if w.contains("suspect not found"))
        );
        let late = found_at(700.0);
        assert!(
            matches!(judge(&spec, &late, 600.0), Verdict::Failure(w) if w.contains("over the 600 s limit"))
        );
        let crash = Observed {
            separation_breaches: 1,
            ..found_at(80.0)
        };
        assert!(failed_for_good(&crash));
        assert!(
            matches!(judge(&spec, &crash, 600.0), Verdict::Failure(w) if w.contains("collision"))
        );
        let obstacle = Observed {
            obstacle_breaches: 3,
            ..found_at(80.0)
        };
        assert!(!judge(&spec, &obstacle, 600.0).is_success());
        let leaked = Observed {
            unchecked_sent: vec!["T4 alfa goto(car_7)".into()],
            ..found_at(80.0)
        };
        assert!(
            matches!(judge(&spec, &leaked, 600.0), Verdict::Failure(w) if w.contains("T4 alfa goto(car_7)"))
        );
    }

    #[test]
    fn take_off_needs_every_drone_up() {
        let spec = SuccessSpec {
            detected: None,
            all_airborne: true,
        };
        let up = Observed {
            all_airborne: true,
            goal_at_s: Some(20.0),
            ..Observed::default()
        };
        assert!(goal_reached(&spec, &up));
        assert_eq!(judge(&spec, &up, 300.0), Verdict::Success);
        let some = Observed {
            all_airborne: false,
            goal_at_s: None,
            ..Observed::default()
        };
        assert!(!goal_reached(&spec, &some));
        assert!(!judge(&spec, &some, 300.0).is_success());
    }

    #[test]
    fn figures_count_cycles_calls_latency_and_tokens() {
        let lines = vec![
            line(
                0.0,
                Record::LlmRequest {
                    layer: "coordinator".into(),
                    attempt: 1,
                    messages: serde_json::json!([]),
                },
            ),
            line(1.0, reply(1000)),
            line(
                1.1,
                Record::LlmRequest {
                    layer: "supervisor".into(),
                    attempt: 1,
                    messages: serde_json::json!([]),
                },
            ),
            line(2.0, reply(3000)),
            line(
                2.1,
                Record::ActionSent {
                    drone: "alfa".into(),
                    task: Some("T1".into()),
                    seq: 1,
                    action: "goto(1, 2, 3)".into(),
                    checked: None,
                },
            ),
            line(2.2, cycle(&["T1 alfa goto(car_1)"])),
            line(5.0, cycle(&[])),
        ];
        let f = log_figures(&lines);
        assert_eq!(
            (
                f.cycles,
                f.model_calls,
                f.replies,
                f.latency_ms_total,
                f.prompt_tokens,
                f.completion_tokens,
                f.actions_sent
            ),
            (2, 2, 2, 4000, 200, 20, 1)
        );
    }

    #[test]
    fn the_audit_catches_what_the_gate_would_not_have_let_through() {
        use crate::safety::DroneSeen;
        use tacos_shared::action::Action;
        use tacos_shared::{DroneMode, Vec3};
        let gate =
            SafetyGate::new(tacos_shared::scenario::Scenario::builtin("city").expect("city"));
        let flying = DroneSeen {
            mode: DroneMode::Flying,
            fresh: true,
            autopilot_link: true,
        };
        let sent = |t: f64, drone: &str, action: Action, seen: DroneSeen| {
            line(
                t,
                Record::ActionSent {
                    drone: drone.into(),
                    task: Some("T1".into()),
                    seq: 7,
                    action: action.to_string(),
                    checked: Some(SentCheck { action, seen }),
                },
            )
        };
        let goto = |x, y, z| Action::Goto {
            target: Vec3::new(x, y, z),
        };
        let clean = vec![
            sent(
                1.0,
                "alfa",
                Action::ArmTakeoff,
                DroneSeen {
                    mode: DroneMode::Idle,
                    ..flying
                },
            ),
            sent(9.0, "alfa", goto(-40.0, -100.0, 10.0), flying),
            // A landing for a drone whose status had gone stale is what the gate allows.
            sent(
                12.0,
                "alfa",
                Action::Land,
                DroneSeen {
                    fresh: false,
                    ..flying
                },
            ),
        ];
        assert!(unchecked_sends(&clean, &gate).is_empty());
        // Into a skyscraper, to a drone on the ground, to one without its autopilot, to a
        // drone that does not exist, a goto on a stale status, and with no record of the
        // check: each is caught.
        let leaked = vec![
            sent(1.0, "alfa", goto(18.0, 18.0, 20.0), flying),
            sent(
                2.0,
                "bravo",
                goto(-40.0, -100.0, 10.0),
                DroneSeen {
                    mode: DroneMode::Idle,
                    ..flying
                },
            ),
            sent(
                3.0,
                "charlie",
                Action::Land,
                DroneSeen {
                    autopilot_link: false,
                    ..flying
                },
            ),
            sent(4.0, "zulu", Action::Land, flying),
            sent(
                4.5,
                "alfa",
                goto(-40.0, -100.0, 10.0),
                DroneSeen {
                    fresh: false,
                    ..flying
                },
            ),
            line(
                5.0,
                Record::ActionSent {
                    drone: "alfa".into(),
                    task: None,
                    seq: 8,
                    action: "land()".into(),
                    checked: None,
                },
            ),
        ];
        let found = unchecked_sends(&leaked, &gate);
        assert_eq!(found.len(), 6, "{found:#?}");
        assert!(
            found[0].contains("goto(18.0, 18.0, 20.0) to alfa"),
            "{}",
            found[0]
        );
        assert!(
            found[5].contains("no record of the gate's check"),
            "{}",
            found[5]
        );
        // A record whose text and typed action disagree is caught too.
        let mut forged = sent(6.0, "alfa", goto(-40.0, -100.0, 10.0), flying);
        if let Record::ActionSent { action, .. } = &mut forged.record {
            *action = "land()".into();
        }
        assert_eq!(unchecked_sends(&[forged], &gate).len(), 1);
    }
}
