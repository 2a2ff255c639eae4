//! The script format (pure): one step per line, `#` starts a comment. See `script` for the
//! grammar. Parsing knows no map; [`Script::check`] then checks the names against one.

use std::fmt;
use std::time::Duration;
use tacos_shared::scenario::Scenario;

/// How long `wait until` waits when the line gives no `within`: a few calls of a slow model.
pub const DEFAULT_WITHIN: Duration = Duration::from_secs(600);

#[derive(Debug, Clone, PartialEq)]
pub struct Script {
    pub steps: Vec<Step>,
}

/// One step, with the line it came from (1-based) and that line's text, for messages.
#[derive(Debug, Clone, PartialEq)]
pub struct Step {
    pub line: usize,
    pub text: String,
    pub kind: StepKind,
}

#[derive(Debug, Clone, PartialEq)]
pub enum StepKind {
    /// A pilot line, exactly as typed (direct commands included).
    Say(String),
    /// Let time pass.
    Wait(Duration),
    /// Wait (bounded) until the condition holds.
    WaitUntil {
        condition: Condition,
        within: Duration,
    },
    /// The condition must hold now.
    Expect(Condition),
    /// Inject a vehicle failure in the simulator (the vehicle dies for good).
    Fail(Victim),
}

/// Which drone a `fail` step kills.
#[derive(Debug, Clone, PartialEq)]
pub enum Victim {
    Drone(String),
    /// The first drone (in the map's order) in this state when the step runs.
    One(DroneState),
}

/// Which drones a condition counts.
#[derive(Debug, Clone, PartialEq)]
pub enum Who {
    /// Every drone of the run except those a `fail` step killed (at least one).
    All,
    /// At least one drone.
    Any,
    /// At least this many drones.
    AtLeast(usize),
    /// This drone.
    Drone(String),
}

#[derive(Debug, Clone, PartialEq)]
pub enum DroneState {
    /// In the air: flying or tracking.
    Flying,
    /// On the ground and available (idle).
    Landed,
    /// Following a target (any, or the one named).
    Tracking(Option<String>),
    Unavailable,
    /// Horizontally near a landmark or a visible target (see `run`).
    Near(String),
}

#[derive(Debug, Clone, PartialEq)]
pub enum Condition {
    Drones {
        who: Who,
        state: DroneState,
    },
    /// The simulator's perception reported this target (since the script started).
    Detected(String),
    /// A plan completed since the last `say`.
    PlanComplete,
    /// The Coordinator made a new plan since the last `fail` step: the automatic replan.
    Replanned,
    /// The simulator's ground truth shows no separation or obstacle breach.
    NoBreaches,
}

#[derive(Debug, Clone, PartialEq, Eq)]
pub struct ParseError {
    pub line: usize,
    pub message: String,
}

impl fmt::Display for ParseError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "line {}: {}", self.line, self.message)
    }
}

impl std::error::Error for ParseError {}

impl fmt::Display for Who {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Who::All => write!(f, "all drones"),
            Who::Any => write!(f, "some drone"),
            Who::AtLeast(n) => write!(f, "at least {n} drones"),
            Who::Drone(d) => write!(f, "{d}"),
        }
    }
}

impl fmt::Display for DroneState {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            DroneState::Flying => write!(f, "flying"),
            DroneState::Landed => write!(f, "landed"),
            DroneState::Tracking(None) => write!(f, "tracking"),
            DroneState::Tracking(Some(t)) => write!(f, "tracking {t}"),
            DroneState::Unavailable => write!(f, "unavailable"),
            DroneState::Near(p) => write!(f, "near {p}"),
        }
    }
}

impl fmt::Display for Condition {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Condition::Drones { who, state } => write!(f, "{who} {state}"),
            Condition::Detected(t) => write!(f, "detected {t}"),
            Condition::PlanComplete => write!(f, "plan complete"),
            Condition::Replanned => write!(f, "replanned"),
            Condition::NoBreaches => write!(f, "no breaches"),
        }
    }
}

const CONDITIONS: &str = "expected a condition: <who> flying | landed | tracking [<target>] | unavailable | near <place>; detected <target>; plan complete; replanned; no breaches";

/// Parses a script; the first error names its line.
pub fn parse(text: &str) -> Result<Script, ParseError> {
    let mut steps = Vec::new();
    for (i, raw) in text.lines().enumerate() {
        let line = i + 1;
        let content = match raw.find('#') {
            Some(at) => &raw[..at],
            None => raw,
        }
        .trim();
        if content.is_empty() {
            continue;
        }
        let kind = parse_step(content).map_err(|message| ParseError { line, message })?;
        steps.push(Step {
            line,
            text: content.to_owned(),
            kind,
        });
    }
    if steps.is_empty() {
        return Err(ParseError {
            line: text.lines().count().max(1),
            message: "the script has no steps".into(),
        });
    }
    Ok(Script { steps })
}

fn parse_step(content: &str) -> Result<StepKind, String> {
    let (keyword, rest) = match content.split_once(char::is_whitespace) {
        Some((k, r)) => (k, r.trim()),
        None => (content, ""),
    };
    let words: Vec<String> = rest.split_whitespace().map(str::to_lowercase).collect();
    let words: Vec<&str> = words.iter().map(String::as_str).collect();
    match keyword.to_lowercase().as_str() {
        "say" if rest.is_empty() => Err("`say` needs the pilot's words".into()),
        "say" => Ok(StepKind::Say(rest.to_owned())),
        // The pilot's answers to a plan held for approval (`--confirm`), said as lines.
        "approve" if rest.is_empty() => Ok(StepKind::Say("approve".into())),
        "approve" => Err("`approve` takes no words (`drop <task>` is said with `say`)".into()),
        "reject" => Ok(StepKind::Say(
            format!("reject {rest}").trim_end().to_owned(),
        )),
        "wait" => match words.as_slice() {
            ["until", condition @ ..] => {
                let (condition, within) = match condition {
                    [c @ .., "within", s] => (c, seconds(s)?),
                    c => (c, DEFAULT_WITHIN),
                };
                Ok(StepKind::WaitUntil {
                    condition: parse_condition(condition)?,
                    within,
                })
            }
            [s] => Ok(StepKind::Wait(seconds(s)?)),
            _ => Err(
                "expected `wait <seconds>` or `wait until <condition> [within <seconds>]`".into(),
            ),
        },
        "expect" => Ok(StepKind::Expect(parse_condition(&words)?)),
        "fail" => match words.as_slice() {
            ["one", state @ ..] => Ok(StepKind::Fail(Victim::One(parse_state(state)?))),
            [drone] if is_name(drone) => Ok(StepKind::Fail(Victim::Drone((*drone).to_owned()))),
            _ => Err("expected `fail <drone>` or `fail one <state>`".into()),
        },
        other => Err(format!(
            "unknown step {other:?}: expected say, approve, reject, wait, expect or fail"
        )),
    }
}

fn seconds(word: &str) -> Result<Duration, String> {
    let s = word.strip_suffix('s').unwrap_or(word);
    match s.parse::<f64>() {
        Ok(v) if (0.0..=86_400.0).contains(&v) => Ok(Duration::from_secs_f64(v)),
        _ => Err(format!("{word:?} is not a number of seconds (0 to 86400)")),
    }
}

fn is_name(word: &str) -> bool {
    !word.is_empty()
        && word
            .chars()
            .all(|c| c.is_ascii_alphanumeric() || c == '_' || c == '-')
}

fn parse_condition(words: &[&str]) -> Result<Condition, String> {
    match words {
        ["plan", "complete"] => Ok(Condition::PlanComplete),
        ["replanned"] => Ok(Condition::Replanned),
        ["no", "breaches"] => Ok(Condition::NoBreaches),
        ["detected", target] if is_name(target) => Ok(Condition::Detected((*target).to_owned())),
        [who, rest @ ..] if !rest.is_empty() => {
            let who = match *who {
                "all" => Who::All,
                "any" | "some" => Who::Any,
                n if n.parse::<usize>().is_ok() => match n.parse::<usize>() {
                    Ok(0) => return Err("a count of drones must be at least 1".into()),
                    Ok(n) => Who::AtLeast(n),
                    Err(_) => return Err(CONDITIONS.into()),
                },
                d if is_name(d) => Who::Drone(d.to_owned()),
                _ => return Err(CONDITIONS.into()),
            };
            // "all drones are flying" reads as well as "all flying".
            let rest: Vec<&str> = rest
                .iter()
                .copied()
                .skip_while(|w| matches!(*w, "drone" | "drones" | "is" | "are"))
                .collect();
            Ok(Condition::Drones {
                who,
                state: parse_state(&rest)?,
            })
        }
        _ => Err(CONDITIONS.into()),
    }
}

fn parse_state(words: &[&str]) -> Result<DroneState, String> {
    match words {
        ["flying"] => Ok(DroneState::Flying),
        ["landed"] => Ok(DroneState::Landed),
        ["tracking"] => Ok(DroneState::Tracking(None)),
        ["tracking", t] if is_name(t) => Ok(DroneState::Tracking(Some((*t).to_owned()))),
        ["unavailable"] => Ok(DroneState::Unavailable),
        ["near", p] if is_name(p) => Ok(DroneState::Near((*p).to_owned())),
        _ => Err(format!(
            "unknown drone state {:?}: expected flying, landed, tracking [<target>], unavailable or near <place>",
            words.join(" ")
        )),
    }
}

impl Script {
    /// Checks every name against the map and the drones of the run, so a typo fails before
    /// the swarm starts, with its line.
    pub fn check(&self, scenario: &Scenario, drones: &[String]) -> Result<(), ParseError> {
        let target = |t: &str| scenario.targets.iter().any(|s| s.name == t);
        let place = |p: &str| scenario.world.landmarks.iter().any(|l| l.name == p) || target(p);
        for step in &self.steps {
            let fail = |message: String| {
                Err(ParseError {
                    line: step.line,
                    message,
                })
            };
            let drone_ok = |d: &str| drones.iter().any(|x| x == d);
            let state_ok = |s: &DroneState| -> Result<(), String> {
                match s {
                    DroneState::Tracking(Some(t)) if !target(t) => Err(format!(
                        "{t:?} is not a target of the {} map",
                        scenario.name
                    )),
                    DroneState::Near(p) if !place(p) => Err(format!(
                        "{p:?} is neither a landmark nor a target of the {} map",
                        scenario.name
                    )),
                    _ => Ok(()),
                }
            };
            let unknown_drone =
                |d: &str| format!("{d:?} is not a drone of this run ({})", drones.join(", "));
            let condition = match &step.kind {
                StepKind::WaitUntil { condition, .. } | StepKind::Expect(condition) => {
                    Some(condition)
                }
                StepKind::Fail(Victim::Drone(d)) if !drone_ok(d) => return fail(unknown_drone(d)),
                StepKind::Fail(Victim::One(state)) => {
                    if let Err(m) = state_ok(state) {
                        return fail(m);
                    }
                    None
                }
                _ => None,
            };
            match condition {
                Some(Condition::Drones { who, state }) => {
                    if let Who::Drone(d) = who
                        && !drone_ok(d)
                    {
                        return fail(unknown_drone(d));
                    }
                    if let Who::AtLeast(n) = who
                        && *n > drones.len()
                    {
                        return fail(format!("this run has only {} drones", drones.len()));
                    }
                    if let Err(m) = state_ok(state) {
                        return fail(m);
                    }
                }
                Some(Condition::Detected(t)) if !target(t) => {
                    return fail(format!(
                        "{t:?} is not a target of the {} map",
                        scenario.name
                    ));
                }
                _ => {}
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn kinds(text: &str) -> Vec<StepKind> {
        match parse(text) {
            Ok(s) => s.steps.into_iter().map(|s| s.kind).collect(),
            Err(e) => panic!("{e}"),
        }
    }

    #[test]
    fn approve_and_reject_are_the_pilot_s_answers_said_as_lines() {
        assert_eq!(
            kinds("approve\nreject bravo stays home\nreject\n"),
            vec![
                StepKind::Say("approve".into()),
                StepKind::Say("reject bravo stays home".into()),
                StepKind::Say("reject".into()),
            ]
        );
        assert!(parse("approve it all\n").is_err());
    }

    #[test]
    fn parses_every_step_kind_with_comments_and_blank_lines() {
        let script = "# take off\n\nsay All drones, take off  # inline comment\nwait 2.5\nwait until all drones are flying within 90s\nexpect alfa near small_park\nfail one tracking van\nfail bravo\nwait until detected dog\nexpect no breaches\nwait until plan complete\nwait until 2 tracking\nexpect replanned\n";
        assert_eq!(
            kinds(script),
            vec![
                StepKind::Say("All drones, take off".into()),
                StepKind::Wait(Duration::from_millis(2500)),
                StepKind::WaitUntil {
                    condition: Condition::Drones {
                        who: Who::All,
                        state: DroneState::Flying
                    },
                    within: Duration::from_secs(90)
                },
                StepKind::Expect(Condition::Drones {
                    who: Who::Drone("alfa".into()),
                    state: DroneState::Near("small_park".into())
                }),
                StepKind::Fail(Victim::One(DroneState::Tracking(Some("van".into())))),
                StepKind::Fail(Victim::Drone("bravo".into())),
                StepKind::WaitUntil {
                    condition: Condition::Detected("dog".into()),
                    within: DEFAULT_WITHIN
                },
                StepKind::Expect(Condition::NoBreaches),
                StepKind::WaitUntil {
                    condition: Condition::PlanComplete,
                    within: DEFAULT_WITHIN
                },
                StepKind::WaitUntil {
                    condition: Condition::Drones {
                        who: Who::AtLeast(2),
                        state: DroneState::Tracking(None)
                    },
                    within: DEFAULT_WITHIN
                },
                StepKind::Expect(Condition::Replanned),
            ]
        );
        let parsed = parse(script).map_err(|e| e.to_string());
        assert_eq!(
            parsed.map(|s| s.steps.iter().map(|s| s.line).collect::<Vec<_>>()),
            Ok(vec![3, 4, 5, 6, 7, 8, 9, 10, 11, 12, 13])
        );
    }

    #[test]
    fn errors_name_the_line_and_what_was_expected() {
        let cases = [
            ("say hi\nwait forever\n", 2, "not a number of seconds"),
            ("\n\nfly to the park\n", 3, "unknown step \"fly\""),
            (
                "wait until all swimming",
                1,
                "unknown drone state \"swimming\"",
            ),
            ("wait until plan complete within soon", 1, "not a number"),
            ("say\n", 1, "needs the pilot's words"),
            ("expect 0 flying", 1, "at least 1"),
            ("expect", 1, "expected a condition"),
            ("fail", 1, "fail <drone>"),
            ("wait -3", 1, "not a number of seconds"),
            ("# only comments\n\n", 2, "no steps"),
        ];
        for (text, line, needle) in cases {
            match parse(text) {
                Ok(s) => panic!("{text:?} parsed as {s:?}"),
                Err(e) => {
                    assert_eq!(e.line, line, "{text:?}: {e}");
                    assert!(e.message.contains(needle), "{text:?}: {e}");
                }
            }
        }
    }

    #[test]
    fn check_names_unknown_drones_places_and_targets_with_their_line() {
        let scenario = match Scenario::builtin("lab") {
            Ok(s) => s,
            Err(e) => panic!("{e}"),
        };
        let drones: Vec<String> = ["alfa", "bravo", "charlie"].map(String::from).to_vec();
        let ok = "say take off\nwait until alfa near small_park\nwait until detected dog\nfail charlie\nexpect 3 landed\n";
        assert_eq!(parse(ok).and_then(|s| s.check(&scenario, &drones)), Ok(()));
        let cases = [
            ("say x\nfail zulu", 2, "\"zulu\" is not a drone"),
            ("expect alfa near car_7", 1, "neither a landmark"),
            ("wait until detected cat", 1, "not a target"),
            ("expect 4 flying", 1, "only 3 drones"),
            ("fail one tracking van", 1, "not a target"),
            ("expect delta flying", 1, "\"delta\" is not a drone"),
        ];
        for (text, line, needle) in cases {
            match parse(text).and_then(|s| s.check(&scenario, &drones)) {
                Ok(()) => panic!("{text:?} passed the check"),
                Err(e) => {
                    assert_eq!(e.line, line, "{text:?}: {e}");
                    assert!(e.message.contains(needle), "{text:?}: {e}");
                }
            }
        }
    }

    /// Every mission script the project ships parses.
    #[test]
    fn the_shipped_mission_scripts_parse() {
        let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("missions");
        let mut n = 0;
        for entry in std::fs::read_dir(&dir).expect("ground/missions") {
            let path = entry.expect("a directory entry").path();
            if path.extension().is_some_and(|e| e == "txt") {
                let text = std::fs::read_to_string(&path).expect("readable");
                if let Err(e) = parse(&text) {
                    panic!("{}: {e}", path.display());
                }
                n += 1;
            }
        }
        assert!(n >= 4, "{n} scripts in {}", dir.display());
    }
}
