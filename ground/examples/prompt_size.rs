//! Prints how large the Coordinator's and the Supervisor's prompts are, in the embedded model's
//! tokens, for 6, 12 and 20 drones of the city (how the cost grows with the swarm).
//! Run: `cargo run -p tacos-ground --example prompt_size`

use tacos_embedded::{EmbeddedBackend, EmbeddedOptions};
use tacos_ground::mission::driver::coordinator_messages;
use tacos_llm::{ChatMessage, ChatRequest};
use tacos_prompts::render::{self, DroneLine, TaskProgress, TaskStatus};
use tacos_prompts::{ActionName, Call, texts};
use tacos_shared::DroneMode;
use tacos_shared::scenario::Scenario;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let city = Scenario::builtin("city")?;
    let model = EmbeddedBackend::load(EmbeddedOptions::from_env())?;
    let world = render::world(&city.world, &[], &[]);
    for n in [6usize, 12, 20] {
        let drones: Vec<DroneLine> = city.drones[..n]
            .iter()
            .map(|d| DroneLine {
                id: d.id.to_string(),
                mode: DroneMode::Flying,
                position: d.home + tacos_shared::Vec3::new(0.0, 0.0, 10.0),
                speed: 0.0,
                action: Some("T1 arm_takeoff()".into()),
                state: Some("done".into()),
            })
            .collect();
        let plan: Vec<(Call, TaskStatus)> = city.drones[..n]
            .iter()
            .enumerate()
            .map(|(i, d)| {
                let call = Call {
                    task: format!("T{}", i + 1),
                    drone: d.id.to_string(),
                    action: ActionName::Goto,
                    target: format!("car_{}", i % 15 + 1),
                    xyz: None,
                };
                (call, TaskStatus::NotStarted)
            })
            .collect();
        let swarm = render::swarm(&drones);
        let coordinator = coordinator_messages(
            render::coordinator_request(
                &swarm,
                &world,
                &render::plan(&plan),
                "(mission start)\n",
                "find the suspect hiding in one of the cars",
                &[],
            ),
            false,
        );
        let supervisor = vec![
            ChatMessage::system(texts::SUPERVISOR),
            ChatMessage::user(render::supervisor_request(
                Some("Search every car, one drone per car."),
                &plan
                    .iter()
                    .map(|(call, status)| TaskProgress {
                        call: call.clone(),
                        status: status.clone(),
                        failures: 0,
                    })
                    .collect::<Vec<_>>(),
                &swarm,
                &world,
            )),
        ];
        let count = |messages: Vec<ChatMessage>| {
            model.count_prompt_tokens(&ChatRequest {
                messages,
                schema: None,
                max_tokens: 1,
                temperature: 0.0,
                seed: None,
                reasoning_effort: None,
            })
        };
        println!(
            "prompt_tokens drones={n} coordinator={} supervisor={}",
            count(coordinator)?,
            count(supervisor)?
        );
    }
    Ok(())
}
