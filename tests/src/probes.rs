//! The mission requests the model benchmarks send: built as the mission engine builds them
//! (`coordinator_messages`, `supervisor_messages`, the schemas of `tacos_prompts`,
//! `MissionConfig`'s token limits, temperature 0 and seed) for six idle drones of the city.

use anyhow::Context;
use serde_json::Value;
use tacos_ground::mission::{MissionConfig, coordinator_messages, grounding, supervisor_messages};
use tacos_llm::{ChatRequest, ResponseSchema};
use tacos_prompts::offer::startable_schema;
use tacos_prompts::render::{self, DroneLine, HistoryEntry, TaskProgress, TaskStatus};
use tacos_prompts::schema::{self, Output};
use tacos_prompts::{ActionName, Call};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneMode, Vec3};

/// Drones of the city in the mission state.
pub const DRONES: usize = 6;

/// One request of the bench.
pub struct Probe {
    pub name: &'static str,
    pub request: ChatRequest,
}

fn request(messages: Vec<tacos_llm::ChatMessage>, output: Output, schema: Value) -> ChatRequest {
    let cfg = MissionConfig::default();
    let floor = match output {
        Output::Coordinator => cfg.coordinator_max_tokens,
        _ => cfg.supervisor_max_tokens,
    };
    ChatRequest {
        messages,
        schema: Some(ResponseSchema {
            name: output.name().into(),
            schema,
        }),
        max_tokens: floor.max(schema::token_budget(output, DRONES)),
        temperature: cfg.temperature,
        seed: cfg.seed,
        reasoning_effort: None,
    }
}

fn take_off(task: usize, drone: &str) -> Call {
    Call {
        task: format!("T{task}"),
        drone: drone.to_owned(),
        action: ActionName::ArmTakeoff,
        target: schema::NO_TARGET.into(),
        xyz: None,
    }
}

/// How the probes' user messages open: the city's map.
pub fn city_request_opening() -> anyhow::Result<String> {
    let city = Scenario::builtin("city").context("the city scenario")?;
    Ok(render::request_opening(&render::world(
        &city.world,
        &[],
        &[],
    )))
}

/// The four mission requests, built as the mission engine builds them for this state, then
/// the decode probe.
pub fn mission_probes() -> anyhow::Result<Vec<Probe>> {
    let city = Scenario::builtin("city").context("the city scenario")?;
    anyhow::ensure!(
        city.drones.len() >= DRONES,
        "the city has {} drones, fewer than {DRONES}",
        city.drones.len()
    );
    let fleet = &city.drones[..DRONES];
    let ids: Vec<String> = fleet.iter().map(|d| d.id.to_string()).collect();
    let world = render::world(&city.world, &[], &[]);
    let on_ground: Vec<DroneLine> = fleet
        .iter()
        .map(|d| DroneLine {
            id: d.id.to_string(),
            mode: DroneMode::Idle,
            position: d.home,
            speed: 0.0,
            action: None,
            state: None,
        })
        .collect();
    let trackable: Vec<String> = city
        .targets
        .iter()
        .filter(|t| t.hidden_at.is_none())
        .map(|t| t.name.clone())
        .collect();
    let places: Vec<String> = city
        .world
        .landmarks
        .iter()
        .map(|l| l.name.clone())
        .chain(trackable.iter().cloned())
        .collect();
    let names: Vec<String> = ids.iter().chain(&places).cloned().collect();
    let coordinator = |instruction: &str| {
        let named =
            render::named_with_kinds(instruction, &names, &render::landmark_kinds(&city.world));
        let scope = grounding::places_in_scope(&places, &named, &[]);
        let messages = coordinator_messages(
            render::coordinator_request(
                &render::swarm(&on_ground),
                &world,
                &render::plan(&[]),
                &render::history(&[HistoryEntry::Pilot(instruction.to_owned())]),
                instruction,
                &named,
            ),
            false,
        );
        let in_scope: Vec<String> = trackable
            .iter()
            .filter(|t| scope.as_ref().is_none_or(|s| s.contains(t)))
            .cloned()
            .collect();
        // As the engine asks with its default aids (`plan-only`: no refusal offered).
        let schema = schema::without_refusal(&schema::build(
            Output::Coordinator,
            &ids,
            scope.as_ref().unwrap_or(&places),
            &in_scope,
        ));
        request(messages, Output::Coordinator, schema)
    };

    let reasoning =
        "The pilot asks every drone to take off: one arm_takeoff per drone, all at once.";
    let plan: Vec<Call> = ids
        .iter()
        .enumerate()
        .map(|(i, id)| take_off(i + 1, id))
        .collect();
    // Cycle 1: nothing started, every take-off startable (and one must start).
    let progress = |running: usize| -> Vec<TaskProgress> {
        (plan.iter().enumerate())
            .map(|(i, c)| TaskProgress {
                call: c.clone(),
                status: if i < running {
                    TaskStatus::Running
                } else {
                    TaskStatus::NotStarted
                },
                failures: 0,
            })
            .collect()
    };
    let first = render::supervisor_request(
        Some(reasoning),
        &progress(0),
        &render::swarm(&on_ground),
        &world,
    );
    // A later cycle: the first three took off (climbing), the other three startable.
    let running = 3;
    let climbing: Vec<DroneLine> = on_ground
        .iter()
        .zip(&plan)
        .enumerate()
        .map(|(i, (d, call))| {
            if i < running {
                DroneLine {
                    mode: DroneMode::Flying,
                    position: d.position + Vec3::new(0.0, 0.0, 4.0),
                    speed: 1.5,
                    // As the engine shows a drone's action: its task and the action.
                    action: Some(format!("{} arm_takeoff()", call.task)),
                    state: Some("running 40%".into()),
                    ..d.clone()
                }
            } else {
                d.clone()
            }
        })
        .collect();
    let later = render::supervisor_request(
        Some(reasoning),
        &progress(running),
        &render::swarm(&climbing),
        &world,
    );
    Ok(vec![
        Probe {
            name: "coordinator cold",
            request: coordinator("all drones take off"),
        },
        Probe {
            name: "coordinator cached",
            request: coordinator("take off with every drone"),
        },
        Probe {
            name: "supervisor cold",
            request: request(
                supervisor_messages(first),
                Output::Supervisor,
                startable_schema(&plan),
            ),
        },
        Probe {
            name: "supervisor cached",
            request: request(
                supervisor_messages(later),
                Output::Supervisor,
                startable_schema(&plan[running..]),
            ),
        },
        // Decoding alone: a short prompt, no schema, a reply that ends by itself (a cut-off
        // reply is an error for both backends; a copy ends where the text does). Greedy on the same weights, both should write
        // the same text; no grammar step, no forced token.
        Probe {
            name: "decode, no schema",
            request: ChatRequest {
                messages: vec![
                    tacos_llm::ChatMessage::system("You are a helpful assistant."),
                    tacos_llm::ChatMessage::user(
                        "Copy this text exactly, and write nothing else: A drone swarm takes off \
                         from the city square at dawn. Each drone climbs to ten metres, turns north \
                         and waits for its next order. The pilot watches the map, names a car, and \
                         two drones fly to it while the others hold their places above the park. \
                         When the search is over, every drone returns to its home and lands.",
                    ),
                ],
                schema: None,
                max_tokens: 600,
                temperature: 0.0,
                seed: MissionConfig::default().seed,
                reasoning_effort: None,
            },
        },
    ])
}
