//! Compact renderings of the mission state for prompts. Small models read short, regular lines
//! best, and the prompt must stay small as the swarm grows (one line per drone, landmarks
//! grouped by kind).

use crate::reply::Call;
use std::collections::BTreeMap;
use std::fmt::Write;
use tacos_shared::messages::TargetObservation;
use tacos_shared::world::World;
use tacos_shared::{DroneMode, Vec3};

/// One drone as the models see it.
#[derive(Debug, Clone, PartialEq)]
pub struct DroneLine {
    pub id: String,
    pub mode: DroneMode,
    pub position: Vec3,
    pub speed: f64,
    /// The task and action it is on (or last did), e.g. `T2 goto(car_7)`.
    pub action: Option<String>,
    /// `running 40%`, `done`, `failed: unreachable …`.
    pub state: Option<String>,
}

/// Where a plan task stands.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TaskStatus {
    NotStarted,
    Running,
    Done,
    Failed(String),
}

impl TaskStatus {
    fn label(&self) -> String {
        match self {
            TaskStatus::NotStarted => "not started".into(),
            TaskStatus::Running => "running".into(),
            TaskStatus::Done => "done".into(),
            TaskStatus::Failed(why) => format!("failed: {why}"),
        }
    }
}

/// What the Coordinator remembers of the mission.
#[derive(Debug, Clone, PartialEq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum HistoryEntry {
    Pilot(String),
    Plan { reasoning: String, plan: Vec<Call> },
    Event(String),
    Executed { call: Call, outcome: String },
}

fn p(v: &Vec3) -> String {
    format!("({:.0}, {:.0}, {:.0})", v.x, v.y, v.z)
}

pub fn swarm(drones: &[DroneLine]) -> String {
    let mut out = String::new();
    for d in drones {
        let _ = write!(out, "- {}: {} at {}", d.id, d.mode, p(&d.position));
        if d.speed > 0.3 {
            let _ = write!(out, ", speed {:.1} m/s", d.speed);
        }
        match (&d.action, &d.state) {
            (Some(a), Some(s)) => {
                let _ = write!(out, "; last action {a}: {s}");
            }
            _ => out.push_str("; no action yet"),
        }
        out.push('\n');
    }
    if drones.is_empty() {
        out.push_str("- (no drones)\n");
    }
    out
}

/// The world as a request shows it, in two parts.
#[derive(Debug, Clone, PartialEq)]
pub struct WorldText {
    /// The flight area, obstacles and landmarks: fixed for a mission, so every request puts it
    /// first after the fixed messages, where a backend that keeps the key/value cache of a
    /// prompt's beginning (the embedded model, llama.cpp's server) computes it once per mission
    /// instead of at every call. After the plan or the swarm, which change between calls, it
    /// was computed again each time (the models bench's later Supervisor cycle computed 954 of
    /// its 1,716 tokens then, 301 of 1,803 with the map first).
    pub map: String,
    /// What changes: the moving targets as last seen, and the mission's events; `(none)`.
    pub live: String,
}

pub fn world(world: &World, targets: &[TargetObservation], events: &[String]) -> WorldText {
    WorldText {
        map: map(world),
        live: live(targets, events),
    }
}

fn map(world: &World) -> String {
    let b = &world.bounds;
    let mut out = format!(
        "Flight area: x {:.0}..{:.0}, y {:.0}..{:.0}, z {:.0}..{:.0} m (+y is north, z is up).\n",
        b.min.x, b.max.x, b.min.y, b.max.y, b.min.z, b.max.z
    );
    if !world.obstacles.is_empty() {
        out.push_str("Obstacles (never fly into them):");
        for o in &world.obstacles {
            let (axes, _) = o.principal_axes();
            let _ = write!(
                out,
                " {} at ({:.0}, {:.0}) radius {:.0} m;",
                o.name,
                o.center.x,
                o.center.y,
                axes.x.min(axes.y)
            );
        }
        out.push('\n');
    }
    let mut by_kind: BTreeMap<&str, Vec<String>> = BTreeMap::new();
    for l in &world.landmarks {
        by_kind.entry(l.kind.as_str()).or_default().push(format!(
            "{} ({:.0}, {:.0})",
            l.name, l.position.x, l.position.y
        ));
    }
    out.push_str("Landmarks:\n");
    for (kind, names) in by_kind {
        // "of kind": the 1.5B model, shown "- park: small_park (…)", took "park" for a name.
        let _ = writeln!(out, "- of kind {kind}: {}", names.join(", "));
    }
    out
}

fn live(targets: &[TargetObservation], events: &[String]) -> String {
    let mut out = String::new();
    if !targets.is_empty() {
        out.push_str("Moving targets:");
        for t in targets {
            let _ = write!(
                out,
                " {} at {} moving ({:.1}, {:.1}) m/s;",
                t.name,
                p(&t.position),
                t.velocity.x,
                t.velocity.y
            );
        }
        out.push('\n');
    }
    for e in events {
        let _ = writeln!(out, "Event: {e}");
    }
    if out.is_empty() {
        out.push_str("(none)\n");
    }
    out
}

pub fn plan(tasks: &[(Call, TaskStatus)]) -> String {
    if tasks.is_empty() {
        return "(none)\n".into();
    }
    let mut out = String::new();
    for (call, status) in tasks {
        let _ = writeln!(out, "- {call}: {}", status.label());
    }
    out
}

pub fn history(entries: &[HistoryEntry]) -> String {
    if entries.is_empty() {
        return "(mission start)\n".into();
    }
    let mut out = String::new();
    for e in entries {
        match e {
            HistoryEntry::Pilot(text) => {
                let _ = writeln!(out, "[pilot] {text}");
            }
            HistoryEntry::Plan { reasoning, plan } => {
                let calls: Vec<String> = plan.iter().map(|c| c.to_string()).collect();
                let _ = writeln!(out, "[plan] {reasoning} => {}", calls.join("; "));
            }
            HistoryEntry::Event(text) => {
                let _ = writeln!(out, "[event] {text}");
            }
            HistoryEntry::Executed { call, outcome } => {
                let _ = writeln!(out, "[executed] {call}: {outcome}");
            }
        }
    }
    out
}

/// The Coordinator's user message.
pub fn coordinator_request(
    swarm_text: &str,
    world: &WorldText,
    pending: &str,
    history_text: &str,
    instruction: &str,
    named: &[String],
) -> String {
    // The map first (see `WorldText::map`); the rest in the order it had, the history next to
    // the instruction (moved before the swarm, the 1.5B model's plans got worse: b612e8f).
    format!(
        "## World\n{}\n## Swarm state\n{swarm_text}\n## Targets and events\n{}\n## Pending plan\n{pending}\n## History\n{history_text}\n## Instruction\n{instruction}\n{}\n",
        world.map,
        world.live,
        named_section(named)
    )
}

/// The "Named in the instruction" section (see [`named_in`]), as requests and few-shot examples
/// both show it.
pub fn named_section(named: &[String]) -> String {
    let list = if named.is_empty() {
        "(none)".to_owned()
    } else {
        named.join(", ")
    };
    format!("## Named in the instruction\n{list}")
}

/// The drones, landmarks and targets among `names` that `instruction` names, as whole words in
/// any case, in the order given: the entities a plan must be about, spelled as the API wants
/// them (a small model copies a name from a short list more reliably than from the prose).
pub fn named_in(instruction: &str, names: &[String]) -> Vec<String> {
    let words: Vec<String> = instruction
        .split(|c: char| !(c.is_alphanumeric() || c == '_'))
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect();
    let mut out: Vec<String> = Vec::new();
    for name in names {
        if words.iter().any(|w| *w == name.to_lowercase()) && !out.contains(name) {
            out.push(name.clone());
        }
    }
    out
}

/// The Supervisor's user message. `reasoning` is `None` in the `wor` ablation.
pub fn supervisor_request(
    reasoning: Option<&str>,
    plan_text: &str,
    swarm_text: &str,
    world: &WorldText,
    memory: &[String],
) -> String {
    // The map first (see `WorldText::map`), then the rest in the order it had.
    let mut out = format!("## World\n{}\n", world.map);
    if let Some(r) = reasoning {
        let _ = write!(out, "## Coordinator's reasoning\n{r}\n\n");
    }
    let _ = write!(
        out,
        "## Plan\n{plan_text}\n## Swarm state\n{swarm_text}\n## Targets and events\n{}\n## Your memory for this plan\n",
        world.live
    );
    if memory.is_empty() {
        out.push_str("(nothing issued yet)\n");
    }
    for m in memory {
        let _ = writeln!(out, "- {m}");
    }
    out
}

/// The monolithic model's user message: instructions, state, and executed actions only.
pub fn monolithic_request(
    instructions: &[String],
    swarm_text: &str,
    world: &WorldText,
    executed: &[String],
) -> String {
    // The map first (see `WorldText::map`), the rest in the order it had.
    let mut out = format!("## World\n{}\n## Pilot's instructions\n", world.map);
    for i in instructions {
        let _ = writeln!(out, "- {i}");
    }
    let _ = write!(
        out,
        "\n## Swarm state\n{swarm_text}\n## Targets and events\n{}\n## Executed actions\n",
        world.live
    );
    if executed.is_empty() {
        out.push_str("(none)\n");
    }
    for e in executed {
        let _ = writeln!(out, "- {e}");
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::scenario::Scenario;

    #[test]
    fn the_city_renders_every_landmark_once() {
        let city = Scenario::builtin("city").expect("city");
        let text = world(&city.world, &[], &["suspect seen at car_7 by alfa".into()]);
        for l in &city.world.landmarks {
            assert_eq!(
                text.map.matches(&format!("{} (", l.name)).count(),
                1,
                "{}",
                l.name
            );
        }
        assert!(text.live.contains("Event: suspect seen at car_7"));
        assert!(text.map.contains("skyscraper_1 at (-18, -18) radius 8 m"));
        assert_eq!(world(&city.world, &[], &[]).live, "(none)\n");
    }

    /// The map comes before anything that changes between calls, so that consecutive requests
    /// of a mission share their beginning through it (a prefix cache then skips it).
    #[test]
    fn requests_share_their_beginning_through_the_map() {
        let city = Scenario::builtin("city").expect("city");
        let common =
            |a: &str, b: &str| a.bytes().zip(b.bytes()).take_while(|(x, y)| x == y).count();
        let before = world(&city.world, &[], &[]);
        let after = world(&city.world, &[], &["alfa lost".into()]);
        let line = |mode| DroneLine {
            id: "alfa".into(),
            mode,
            position: Vec3::new(1.0, 2.0, 0.0),
            speed: 0.0,
            action: None,
            state: None,
        };
        let (idle, flying) = (
            swarm(&[line(DroneMode::Idle)]),
            swarm(&[line(DroneMode::Flying)]),
        );
        let shared = "## World\n".len() + before.map.len();

        let a = supervisor_request(Some("r"), "- T1: not started\n", &idle, &before, &[]);
        let b = supervisor_request(Some("r"), "- T1: running\n", &flying, &after, &[]);
        assert!(common(&a, &b) > shared, "{a}\n---\n{b}");

        let a = coordinator_request(&idle, &before, "(none)\n", "h\n", "take off", &[]);
        let b = coordinator_request(&flying, &after, "(none)\n", "h\nmore\n", "land", &[]);
        assert!(common(&a, &b) > shared, "{a}\n---\n{b}");

        let a = monolithic_request(&["i".into()], &idle, &before, &[]);
        let b = monolithic_request(&["i".into()], &flying, &after, &["x".into()]);
        assert!(common(&a, &b) > shared, "{a}\n---\n{b}");
    }

    #[test]
    fn names_in_an_instruction_are_whole_words() {
        let names: Vec<String> = ["alfa", "car_1", "car_12", "small_park", "van"]
            .map(String::from)
            .to_vec();
        assert_eq!(
            named_in("Alfa, check car_12 and the Small_Park; vanish", &names),
            ["alfa", "car_12", "small_park"]
        );
        assert!(named_in("all drones take off", &names).is_empty());
        let w = WorldText {
            map: "m".into(),
            live: "l".into(),
        };
        let text = coordinator_request("s", &w, "p", "h", "i", &[]);
        assert!(text.ends_with("## Named in the instruction\n(none)\n"));
    }

    #[test]
    fn swarm_lines_are_compact() {
        let line = DroneLine {
            id: "alfa".into(),
            mode: DroneMode::Flying,
            position: Vec3::new(1.0, 2.0, 10.0),
            speed: 0.0,
            action: Some("T1 alfa arm_takeoff()".into()),
            state: Some("done".into()),
        };
        assert_eq!(
            swarm(&[line]),
            "- alfa: flying at (1, 2, 10); last action T1 alfa arm_takeoff(): done\n"
        );
    }
}
