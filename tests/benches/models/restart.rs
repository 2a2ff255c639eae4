//! A ground station started again: the first Coordinator and Supervisor calls of a process whose
//! prompt store (`tacos_embedded::EmbeddedOptions::prompt_store`) holds the fixed beginnings that
//! an earlier process's warm-up left there, as `tacos-ground` keeps them.

use std::path::Path;
use std::time::{Duration, Instant};

use anyhow::Context;
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions, GenerationStats};
use tacos_ground::mission::{coordinator_fixed_messages, supervisor_fixed_messages};
use tacos_llm::{ChatReply, ChatRequest, LlmBackend, PromptBeginning};

/// One call of the restarted process.
pub struct RestartedCall {
    pub latency: Duration,
    pub prompt_tokens: u32,
    /// Prompt tokens read back from the store or kept from the call before.
    pub reused_tokens: u32,
}

pub struct Restarted {
    pub coordinator: RestartedCall,
    pub supervisor: RestartedCall,
}

fn call(backend: &EmbeddedBackend, request: &ChatRequest) -> anyhow::Result<RestartedCall> {
    let (reply, stats): (ChatReply, GenerationStats) = backend.chat_blocking(request)?;
    Ok(RestartedCall {
        latency: reply.latency,
        prompt_tokens: reply.usage.prompt_tokens,
        reused_tokens: stats.reused_tokens,
    })
}

/// Waits for `n` whole entries (`.tokens` files) in `dir`: the store writes on a thread of its
/// own after the warm-up.
fn wait_for_entries(dir: &Path, n: usize, limit: Duration) -> anyhow::Result<()> {
    let deadline = Instant::now() + limit;
    loop {
        let entries = std::fs::read_dir(dir)
            .map(|d| {
                d.flatten()
                    .filter(|e| e.path().extension().is_some_and(|x| x == "tokens"))
                    .count()
            })
            .unwrap_or(0);
        if entries >= n {
            return Ok(());
        }
        anyhow::ensure!(
            Instant::now() < deadline,
            "{entries} of {n} prompt beginnings stored in {} after {limit:?}",
            dir.display()
        );
        std::thread::sleep(Duration::from_millis(100));
    }
}

/// A first process warms up both layers' fixed beginnings (their messages, then `user_opening`:
/// the map) into an empty store and exits; a second, loaded afresh, answers the cold
/// `coordinator` request, then the cold `supervisor` one.
pub fn first_calls_after_a_restart(
    model: EmbeddedModel,
    repeat_penalty: f32,
    coordinator: &ChatRequest,
    supervisor: &ChatRequest,
    user_opening: &str,
) -> anyhow::Result<Restarted> {
    let dir = std::env::temp_dir().join(format!("tacos-bench-prompts-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    let options = || EmbeddedOptions {
        model,
        repeat_penalty,
        prompt_store: Some(dir.clone()),
        ..EmbeddedOptions::from_env()
    };
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .context("a runtime for the warm-up")?;
    {
        let first =
            EmbeddedBackend::load(options()).context("loading the first process's model")?;
        // As the mission engine warms up with its default aids (`plan-only`: no refusal
        // offered): each layer's fixed messages, then the map opening the user turn.
        let beginning = |messages| PromptBeginning {
            messages,
            user_opening: user_opening.to_owned(),
        };
        runtime.block_on(async {
            first
                .warm_up(&beginning(coordinator_fixed_messages(false)))
                .await?;
            first.warm_up(&beginning(supervisor_fixed_messages())).await
        })?;
        wait_for_entries(&dir, 2, Duration::from_secs(120))?;
    }
    let second = EmbeddedBackend::load(options()).context("loading the restarted model")?;
    let restarted = Restarted {
        coordinator: call(&second, coordinator).context("the restarted Coordinator call")?,
        supervisor: call(&second, supervisor).context("the restarted Supervisor call")?,
    };
    let _ = std::fs::remove_dir_all(&dir);
    Ok(restarted)
}
