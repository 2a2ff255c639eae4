//! Asks the embedded model's Coordinator once per instruction, with every drone of the map
//! flying above its home, and prints the plan it makes: a quick way to see how the small model
//! reads a pilot line before writing it into a mission script.
//! Run: `cargo run -p tacos-ground --example coordinator_probe -- lab "alfa, check small_park"`
//! (`PROBE_ON_THE_GROUND=1` for a swarm that has not taken off, `PROBE_OFFER_REFUSAL=1` for the
//! prompt and schema that let a reply decline, as with `--aids none`; `PROBE_TEMPERATURE=0.7`
//! to sample as `tacos-ground eval` does, each instruction with its own seed: repeat one to see
//! several samples).

use tacos_embedded::{EmbeddedBackend, EmbeddedOptions};
use tacos_ground::mission::driver::coordinator_messages;
use tacos_ground::mission::grounding;
use tacos_llm::{ChatRequest, LlmBackend, ResponseSchema};
use tacos_prompts::render::{self, DroneLine, HistoryEntry};
use tacos_prompts::schema::{self, Output};
use tacos_shared::DroneMode;
use tacos_shared::scenario::Scenario;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args = std::env::args().skip(1);
    let map = args.next().unwrap_or_else(|| "lab".into());
    let scenario = Scenario::builtin(&map)?;
    let model = EmbeddedBackend::load(EmbeddedOptions::from_env())?;
    // `PROBE_ON_THE_GROUND=1`: every drone idle at its home instead of flying above it.
    let grounded = std::env::var_os("PROBE_ON_THE_GROUND").is_some();
    let offer_refusal = std::env::var_os("PROBE_OFFER_REFUSAL").is_some();
    let temperature: f32 = match std::env::var("PROBE_TEMPERATURE") {
        Ok(t) => t.parse()?,
        Err(_) => 0.0,
    };
    let drones: Vec<DroneLine> = scenario
        .drones
        .iter()
        .take(6)
        .map(|d| DroneLine {
            id: d.id.to_string(),
            mode: if grounded {
                DroneMode::Idle
            } else {
                DroneMode::Flying
            },
            position: d.home
                + tacos_shared::Vec3::new(
                    0.0,
                    0.0,
                    if grounded {
                        0.0
                    } else {
                        scenario.limits.takeoff_altitude
                    },
                ),
            speed: 0.0,
            action: (!grounded).then(|| format!("T1 {} arm_takeoff()", d.id)),
            state: (!grounded).then(|| "done".into()),
        })
        .collect();
    let ids: Vec<String> = drones.iter().map(|d| d.id.clone()).collect();
    let trackable: Vec<String> = scenario
        .targets
        .iter()
        .filter(|t| t.hidden_at.is_none())
        .map(|t| t.name.clone())
        .collect();
    let places: Vec<String> = scenario
        .world
        .landmarks
        .iter()
        .map(|l| l.name.clone())
        .chain(trackable.iter().cloned())
        .collect();
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()?;
    for (n, instruction) in args.enumerate() {
        let history = render::history(&[HistoryEntry::Pilot(instruction.clone())]);
        let named = render::named_with_kinds(
            &instruction,
            &ids.iter().chain(&places).cloned().collect::<Vec<_>>(),
            &render::landmark_kinds(&scenario.world),
        );
        // As the engine limits it: the places the instruction names, if it names any.
        let scope = grounding::places_in_scope(&places, &named, &[]);
        let messages = coordinator_messages(
            render::coordinator_request(
                &render::swarm(&drones),
                &render::world(&scenario.world, &[], &[]),
                &render::plan(&[]),
                &history,
                &instruction,
                &named,
            ),
            offer_refusal,
        );
        let built = schema::build(
            Output::Coordinator,
            &ids,
            scope.as_ref().unwrap_or(&places),
            &trackable
                .iter()
                .filter(|t| scope.as_ref().is_none_or(|s| s.contains(t)))
                .cloned()
                .collect::<Vec<_>>(),
        );
        let request = ChatRequest {
            messages,
            schema: Some(ResponseSchema {
                name: Output::Coordinator.name().into(),
                schema: if offer_refusal {
                    built
                } else {
                    schema::without_refusal(&built)
                },
            }),
            max_tokens: schema::token_budget(Output::Coordinator, ids.len()),
            temperature,
            seed: Some(7 + n as u64),
            reasoning_effort: None,
        };
        let reply = runtime.block_on(model.chat(&request))?;
        let plan = tacos_prompts::CoordinatorReply::parse(&reply.content)
            .map(|r| {
                let plan = r
                    .plan
                    .iter()
                    .map(|c| c.to_string())
                    .collect::<Vec<_>>()
                    .join("; ");
                let said = match r.refusal_text() {
                    Some(refusal) => format!("{plan} [declined: {refusal}]"),
                    None => plan,
                };
                format!("{said}\n    reasoning: {}", r.reasoning)
            })
            .unwrap_or_else(|e| format!("unparsable: {e}"));
        println!(
            "{instruction:?} ({:.0} s) => {plan}",
            reply.latency.as_secs_f64()
        );
    }
    Ok(())
}
