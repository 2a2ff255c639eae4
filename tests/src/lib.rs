//! The shared test kit for end-to-end tests: unique swarms, a simulated stack on loopback with
//! free ports, and waits that always time out.

use std::time::Duration;
use tacos_ground::launch::{Stack, StackConfig};
use tacos_ground::link::{GroundLink, GroundRole};
use tacos_ground::mission::log::MissionLog;
use tacos_shared::SwarmId;
use tacos_shared::messages::{SimTruth, VehicleTruth};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode};
use tokio::sync::watch;

pub mod chat_server;
pub mod deploy;
pub mod ground_station;
pub mod llama_server;
pub mod netns;
pub mod probes;
pub mod prompt_text;

/// A mission log in a file of its own in the temporary directory, named after `tag`.
pub fn temp_mission_log(
    tag: &str,
) -> anyhow::Result<(std::path::PathBuf, std::sync::Arc<MissionLog>)> {
    let path = std::env::temp_dir().join(format!("{}.jsonl", unique_swarm(tag)));
    let log = std::sync::Arc::new(MissionLog::create(&path)?);
    Ok((path, log))
}

/// A swarm id no other test (or run) uses.
pub fn unique_swarm(tag: &str) -> SwarmId {
    use std::sync::atomic::{AtomicU32, Ordering};
    static NEXT: AtomicU32 = AtomicU32::new(0);
    let n = NEXT.fetch_add(1, Ordering::Relaxed);
    let nanos = std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map_or(0, |d| d.subsec_nanos());
    SwarmId::new(format!("{tag}{}x{n}x{nanos}", std::process::id()))
        .unwrap_or_else(|e| panic!("bad swarm id: {e}"))
}

/// A simulated swarm of `n` drones of `scenario` and a ground link that is its zenoh hub.
pub struct SimSwarm {
    pub link: std::sync::Arc<GroundLink>,
    pub stack: Stack,
    pub scenario: Scenario,
}

impl SimSwarm {
    pub async fn start(tag: &str, scenario_name: &str, n: usize) -> anyhow::Result<SimSwarm> {
        Self::start_with(tag, scenario_name, n, |_| {}).await
    }

    /// A built-in scenario (`city`, `lab`) or a scenario file, as the binaries take it.
    pub async fn start_with(
        tag: &str,
        scenario_name: &str,
        n: usize,
        adjust: impl FnOnce(&mut StackConfig),
    ) -> anyhow::Result<SimSwarm> {
        Self::start_as(tag, scenario_name, n, GroundRole::InControl, adjust).await
    }

    /// A swarm whose hub only watches (`GroundRole::Monitor`): the ground station in control
    /// is another process, joined with [`Self::bus_args`].
    pub async fn start_watching(
        tag: &str,
        scenario_name: &str,
        n: usize,
    ) -> anyhow::Result<SimSwarm> {
        Self::start_as(tag, scenario_name, n, GroundRole::Monitor, |_| {}).await
    }

    async fn start_as(
        tag: &str,
        scenario_name: &str,
        n: usize,
        role: GroundRole,
        adjust: impl FnOnce(&mut StackConfig),
    ) -> anyhow::Result<SimSwarm> {
        let scenario = tacos_bus::load_scenario(scenario_name)?;
        let mut config =
            StackConfig::on_loopback(unique_swarm(tag), scenario_name, scenario.clone(), n)?;
        adjust(&mut config);
        let link = std::sync::Arc::new(GroundLink::connect_as(&config.ground_bus(), role).await?);
        let stack = Stack::start(config)?;
        Ok(SimSwarm {
            link,
            stack,
            scenario,
        })
    }

    /// Waits (up to a minute) until each of `drones` is alive, linked to its autopilot and
    /// idle on the ground; returns their ids.
    pub async fn wait_on_the_ground(
        &self,
        drones: &[&str],
    ) -> anyhow::Result<Vec<tacos_shared::DroneId>> {
        let ids: Vec<tacos_shared::DroneId> = drones
            .iter()
            .map(|d| tacos_shared::DroneId::new(*d))
            .collect::<Result<_, _>>()?;
        self.link
            .wait_for_drones(&ids, Duration::from_secs(60), |s| {
                s.autopilot_link && s.mode == tacos_shared::DroneMode::Idle
            })
            .await?;
        Ok(ids)
    }

    /// Takes `drones` off through `gate` (no model) and waits until each take-off is done.
    pub async fn take_off(
        &self,
        gate: &tacos_ground::safety::SafetyGate,
        drones: &[DroneId],
    ) -> anyhow::Result<()> {
        let takeoffs: Vec<(DroneId, tacos_shared::action::Action)> = drones
            .iter()
            .map(|d| (d.clone(), tacos_shared::action::Action::ArmTakeoff))
            .collect();
        tacos_ground::direct::run_actions(
            &self.link,
            gate,
            &takeoffs,
            None,
            Duration::from_secs(90),
        )
        .await?;
        Ok(())
    }

    /// Sends `drone` a goto `offset` from its home at take-off altitude through `gate`, and
    /// waits for its outcome on a task of its own (the test goes on meanwhile).
    pub fn goto_in_background(
        &self,
        gate: &tacos_ground::safety::SafetyGate,
        drone: &DroneId,
        offset: tacos_shared::Vec3,
        step: Duration,
    ) -> tokio::task::JoinHandle<Result<(), tacos_ground::direct::DirectError>> {
        let home = self
            .scenario
            .drone(drone)
            .map(|s| s.home)
            .unwrap_or_default();
        let target = home
            + offset
            + tacos_shared::Vec3::new(0.0, 0.0, self.scenario.limits.takeoff_altitude);
        let (link, gate, drone) = (self.link.clone(), gate.clone(), drone.clone());
        tokio::spawn(async move {
            let goto = [(drone, tacos_shared::action::Action::Goto { target })];
            tacos_ground::direct::run_actions(&link, &gate, &goto, None, step).await
        })
    }

    /// The arguments that join another process to this swarm through its hub, on the
    /// simulator's clock, as the stack's own processes join it.
    pub fn bus_args(&self) -> Vec<String> {
        vec![
            "--swarm".into(),
            self.stack.config.swarm.to_string(),
            "--zenoh-connect".into(),
            self.stack.config.hub_endpoint.clone(),
            "--sim-clock".into(),
        ]
    }

    pub async fn stop(self) {
        self.stack.shutdown(Duration::from_secs(3)).await;
    }
}

/// A drone id from a literal.
pub fn id(name: &str) -> DroneId {
    DroneId::new(name).unwrap_or_else(|e| panic!("{e}"))
}

/// One vehicle in the simulator's truth.
pub fn vehicle<'a>(truth: &'a SimTruth, drone: &DroneId) -> Option<&'a VehicleTruth> {
    truth.vehicles.iter().find(|v| &v.drone == drone)
}

/// Waits until the truth satisfies `ok`, or fails naming `what`.
pub async fn truth_until(
    truth: &mut watch::Receiver<Option<SimTruth>>,
    limit: Duration,
    what: &str,
    ok: impl Fn(&SimTruth) -> bool,
) -> anyhow::Result<SimTruth> {
    let deadline = tokio::time::Instant::now() + limit;
    loop {
        if let Some(t) = truth.borrow().as_ref().filter(|t| ok(t)) {
            return Ok(t.clone());
        }
        match tokio::time::timeout_at(deadline, truth.changed()).await {
            Ok(Ok(())) => {}
            _ => anyhow::bail!(
                "simulator truth never showed: {what} (last: {:?})",
                truth.borrow().as_ref().map(|t| &t.vehicles)
            ),
        }
    }
}

/// Waits until every drone is up, linked to its autopilot and on the ground.
pub async fn all_ready(sim: &SimSwarm, ids: &[DroneId]) -> anyhow::Result<()> {
    sim.link
        .wait_for_drones(ids, Duration::from_secs(60), |s| {
            s.autopilot_link && s.mode == DroneMode::Idle
        })
        .await?;
    Ok(())
}

/// Waits until a put on `key` from `session` reaches a subscriber: a fresh session's puts
/// reach only the subscribers it already knows of.
pub async fn wait_for_subscriber(session: &zenoh::Session, key: &str) -> anyhow::Result<()> {
    let publisher = session
        .declare_publisher(key.to_owned())
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?;
    let deadline = std::time::Instant::now() + Duration::from_secs(10);
    while !publisher
        .matching_status()
        .await
        .map_err(|e| anyhow::anyhow!("{e}"))?
        .matching()
    {
        if std::time::Instant::now() > deadline {
            anyhow::bail!("no subscriber matched {key} within 10 s");
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
    Ok(())
}

/// Runs `fut` with a deadline, naming what timed out.
pub async fn within<T>(
    what: &str,
    limit: Duration,
    fut: impl std::future::Future<Output = T>,
) -> anyhow::Result<T> {
    tokio::time::timeout(limit, fut)
        .await
        .map_err(|_| anyhow::anyhow!("timed out after {limit:?}: {what}"))
}

/// The next event the pilot is told whose text contains `needle` (within 30 s).
pub async fn told(
    updates: &mut tokio::sync::mpsc::UnboundedReceiver<tacos_ground::mission::MissionUpdate>,
    needle: &str,
) -> anyhow::Result<String> {
    within(
        &format!("an event with {needle:?}"),
        Duration::from_secs(30),
        async {
            while let Some(update) = updates.recv().await {
                if let tacos_ground::mission::MissionUpdate::Event { text, .. } = update
                    && text.contains(needle)
                {
                    return text;
                }
            }
            String::new()
        },
    )
    .await
}

/// A stand-in for a language model that answers from what the prompt says, the way a model
/// would: `policy` sees each request (system prompt, user message, any repair turns) and
/// returns the reply text, or an error as a server would. It records every request.
pub struct PolicyBackend<F> {
    policy: F,
    /// How long each answer takes (20 ms unless [`PolicyBackend::thinking`] says otherwise).
    think: Duration,
    pub requests: std::sync::Mutex<Vec<tacos_llm::ChatRequest>>,
}

impl<F> PolicyBackend<F>
where
    F: Fn(&tacos_llm::ChatRequest) -> Result<String, tacos_llm::LlmError> + Send + Sync,
{
    pub fn new(policy: F) -> Self {
        PolicyBackend {
            policy,
            // A model takes a moment; the engine must not depend on instant answers.
            think: Duration::from_millis(20),
            requests: std::sync::Mutex::new(Vec::new()),
        }
    }

    /// Every answer takes `think`, as the embedded model's take tens of seconds.
    pub fn thinking(mut self, think: Duration) -> Self {
        self.think = think;
        self
    }
}

impl<F> tacos_llm::LlmBackend for PolicyBackend<F>
where
    F: Fn(&tacos_llm::ChatRequest) -> Result<String, tacos_llm::LlmError> + Send + Sync,
{
    fn chat<'a>(
        &'a self,
        request: &'a tacos_llm::ChatRequest,
    ) -> tacos_llm::BoxFuture<'a, Result<tacos_llm::ChatReply, tacos_llm::LlmError>> {
        Box::pin(async move {
            let start = std::time::Instant::now();
            if let Ok(mut log) = self.requests.lock() {
                log.push(request.clone());
            }
            tokio::time::sleep(self.think).await;
            let content = (self.policy)(request)?;
            let words = |t: &str| t.split_whitespace().count() as u32;
            Ok(tacos_llm::ChatReply {
                usage: tacos_llm::Usage {
                    prompt_tokens: request.messages.iter().map(|m| words(&m.content)).sum(),
                    completion_tokens: words(&content),
                },
                content,
                reasoning: None,
                latency: start.elapsed(),
                model: "policy".into(),
            })
        })
    }

    fn describe(&self) -> String {
        "policy test model".into()
    }
}

/// The PX4 SITL build for the tests that fly real PX4, or `None` (the test then returns early,
/// having said how to get one). `$TACOS_PX4_SITL`, else `../shared/px4-sitl`; with `CI=true`
/// a missing build is a failure, since CI always has one.
pub fn px4_sitl_or_skip(test: &str) -> Option<std::path::PathBuf> {
    match tacos_ground::launch::px4::find_px4_sitl(None) {
        Ok(dir) => Some(dir),
        Err(e) if std::env::var("CI").is_ok_and(|v| v == "true") => {
            panic!("{test}: CI must fly real PX4, but {e}")
        }
        Err(e) => {
            eprintln!("SKIPPED {test}: {e}");
            None
        }
    }
}

/// Prints where a failed test's logs are and the last `lines` lines of each of them, so that a
/// failure on a CI machine (whose temporary files are gone afterwards) still shows what the
/// processes said.
pub fn print_log_tails(dir: &std::path::Path, lines: usize) {
    eprintln!("logs: {}", dir.display());
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let mut logs: Vec<_> = entries
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.extension().is_some_and(|x| x == "log"))
        .collect();
    logs.sort();
    for log in logs {
        let Ok(text) = std::fs::read_to_string(&log) else {
            continue;
        };
        let all: Vec<&str> = text.lines().collect();
        let tail = &all[all.len().saturating_sub(lines)..];
        eprintln!("── {} (last {} lines)", log.display(), tail.len());
        for line in tail {
            eprintln!("{line}");
        }
    }
}
