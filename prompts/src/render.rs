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

/// How every request's user message opens: the map (see `WorldText::map`), the same on every call
/// of a mission, so that a prompt cache holds it with the layer's fixed messages.
pub fn request_opening(world: &WorldText) -> String {
    format!("## World\n{}\n", world.map)
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
        "{}## Swarm state\n{swarm_text}\n## Targets and events\n{}\n## Pending plan\n{pending}\n## History\n{history_text}\n## Instruction\n{instruction}\n{}\n",
        request_opening(world),
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
    named_with_kinds(instruction, names, &[])
}

/// [`named_in`], where a landmark kind the instruction says as a word, singular or plural
/// ("one of the cars", "a villa"), names every landmark of that kind among `names`;
/// `landmarks` pairs each landmark's name with its kind. "Find the suspect hiding in one of the
/// cars" is about `car_1` … `car_15`: listed, the 1.5B model's search covers them, and the
/// place scope keeps the plan on them (it chased the van, a moving target, instead).
pub fn named_with_kinds(
    instruction: &str,
    names: &[String],
    landmarks: &[(String, String)],
) -> Vec<String> {
    let words: Vec<String> = instruction
        .split(|c: char| !(c.is_alphanumeric() || c == '_'))
        .filter(|w| !w.is_empty())
        .map(str::to_lowercase)
        .collect();
    let kind_said = |kind: &str| words.iter().any(|w| says_kind(w, kind));
    let of_said_kind = |name: &String| {
        landmarks
            .iter()
            .any(|(n, kind)| n == name && kind_said(kind))
    };
    let mut out: Vec<String> = Vec::new();
    for name in names {
        let said = words.iter().any(|w| *w == name.to_lowercase()) || of_said_kind(name);
        if said && !out.contains(name) {
            out.push(name.clone());
        }
    }
    out
}

/// Whether `word` (lower case) is `kind` or its English plural: car/cars, bus/buses, city/cities.
fn says_kind(word: &str, kind: &str) -> bool {
    let kind = kind.to_lowercase();
    let plural_ies = kind
        .strip_suffix('y')
        .is_some_and(|stem| word.strip_suffix("ies") == Some(stem));
    word == kind
        || word.strip_suffix('s') == Some(kind.as_str())
        || word.strip_suffix("es") == Some(kind.as_str())
        || plural_ies
}

/// Each landmark of `world` with its kind, for [`named_with_kinds`].
pub fn landmark_kinds(world: &World) -> Vec<(String, String)> {
    (world.landmarks.iter())
        .map(|l| (l.name.clone(), l.kind.as_str().to_owned()))
        .collect()
}

/// One task of the plan in force as the Supervisor sees it.
#[derive(Debug, Clone, PartialEq)]
pub struct TaskProgress {
    pub call: Call,
    pub status: TaskStatus,
    /// Times it has failed so far (a failed task may be issued again).
    pub failures: u32,
}

/// The Supervisor's user message. `reasoning` is `None` in the `wor` ablation.
///
/// What changes from cycle to cycle comes last: the plan's calls (fixed while the plan holds),
/// then the swarm, the targets and events, and the Supervisor's memory of the plan: where each
/// task it issued stands, and which it has not issued yet. With the statuses on the plan's
/// lines, and the memory a log of "issued …" and outcome lines beside them, every cycle
/// recomputed the plan and a memory that grew by two lines a task (the models bench's later
/// cycle computes 230 tokens of 1,860 this way, 301 of 1,814 before: 2.7 s of prefill on a
/// 2-core Xeon instead of 3.8).
pub fn supervisor_request(
    reasoning: Option<&str>,
    tasks: &[TaskProgress],
    swarm_text: &str,
    world: &WorldText,
) -> String {
    // The map first (see `WorldText::map`).
    let mut out = request_opening(world);
    if let Some(r) = reasoning {
        let _ = write!(out, "## Coordinator's reasoning\n{r}\n\n");
    }
    out.push_str("## Plan\n");
    if tasks.is_empty() {
        out.push_str("(none)\n");
    }
    for t in tasks {
        let _ = writeln!(out, "- {}", t.call);
    }
    let _ = write!(
        out,
        "## Swarm state\n{swarm_text}\n## Targets and events\n{}\n## Your memory for this plan\n{}",
        world.live,
        plan_memory(tasks)
    );
    out
}

/// The Supervisor's memory of a plan: a line for each task it issued, where it stands (and how
/// often it failed before), then the tasks not issued yet.
pub fn plan_memory(tasks: &[TaskProgress]) -> String {
    let mut out = String::new();
    let mut waiting: Vec<&str> = Vec::new();
    for t in tasks {
        if t.status == TaskStatus::NotStarted {
            waiting.push(&t.call.task);
            continue;
        }
        let _ = write!(out, "- {}: {}", t.call.task, t.status.label());
        match (&t.status, t.failures) {
            (_, 0) => {}
            (TaskStatus::Failed(_), 1) => {}
            (TaskStatus::Failed(_), n) => {
                let _ = write!(out, " ({n} times)");
            }
            (_, 1) => out.push_str(", after 1 failure"),
            (_, n) => {
                let _ = write!(out, ", after {n} failures");
            }
        }
        out.push('\n');
    }
    if waiting.is_empty() {
        out.push_str("- every task issued\n");
    } else {
        let _ = writeln!(out, "- not issued yet: {}", waiting.join(", "));
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
    let mut out = request_opening(world) + "## Pilot's instructions\n";
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

        let task = |status| TaskProgress {
            call: Call {
                task: "T1".into(),
                drone: "alfa".into(),
                action: crate::ActionName::ArmTakeoff,
                target: "none".into(),
                xyz: None,
            },
            status,
            failures: 0,
        };
        let a = supervisor_request(Some("r"), &[task(TaskStatus::NotStarted)], &idle, &before);
        let b = supervisor_request(Some("r"), &[task(TaskStatus::Running)], &flying, &after);
        // The plan's calls too: the statuses are in the memory, after the swarm.
        let through_plan = a.find("## Swarm state").expect("a swarm section");
        assert!(common(&a, &b) >= through_plan, "{a}\n---\n{b}");

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
        let kinds: Vec<(String, String)> =
            [("car_1", "car"), ("car_12", "car"), ("small_park", "park")]
                .map(|(n, k)| (n.to_owned(), k.to_owned()))
                .to_vec();
        // A kind said as a word names every landmark of it; inside a name it says nothing.
        assert_eq!(
            named_with_kinds("Find the suspect in one of the Cars, alfa", &names, &kinds),
            ["alfa", "car_1", "car_12"]
        );
        assert_eq!(
            named_with_kinds("check the car and small_park", &names, &kinds),
            ["car_1", "car_12", "small_park"]
        );
        assert!(named_with_kinds("fly over the parking, carefully", &names, &kinds).is_empty());
        assert!(says_kind("cities", "city") && says_kind("buses", "bus"));
        let w = WorldText {
            map: "m".into(),
            live: "l".into(),
        };
        let text = coordinator_request("s", &w, "p", "h", "i", &[]);
        assert!(text.ends_with("## Named in the instruction\n(none)\n"));
    }

    #[test]
    fn the_memory_says_where_each_issued_task_stands() {
        let call = |task: &str, drone: &str| Call {
            task: task.into(),
            drone: drone.into(),
            action: crate::ActionName::Goto,
            target: "car_1".into(),
            xyz: None,
        };
        let tasks = [
            (call("T1", "alfa"), TaskStatus::Done, 0),
            (
                call("T2", "bravo"),
                TaskStatus::Failed("unreachable".into()),
                2,
            ),
            (call("T3", "charlie"), TaskStatus::Running, 1),
            (call("T4", "delta"), TaskStatus::NotStarted, 0),
            (call("T5", "echo"), TaskStatus::NotStarted, 0),
        ]
        .map(|(call, status, failures)| TaskProgress {
            call,
            status,
            failures,
        });
        assert_eq!(
            plan_memory(&tasks),
            "- T1: done\n- T2: failed: unreachable (2 times)\n- T3: running, after 1 failure\n\
             - not issued yet: T4, T5\n"
        );
        assert!(plan_memory(&tasks[..3]).ends_with("- every task issued\n"));
        let city = Scenario::builtin("city").expect("city");
        let text = supervisor_request(None, &tasks, "- alfa: …\n", &world(&city.world, &[], &[]));
        assert!(
            text.contains("## Plan\n- T1 alfa goto(car_1)\n- T2 bravo goto(car_1)\n"),
            "{text}"
        );
        assert!(!text.contains("reasoning"), "{text}");
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
