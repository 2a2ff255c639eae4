//! `tacos-ground send`: one action to one drone, through the safety gate, and its outcome.

use crate::link::GroundLink;
use crate::safety::SafetyGate;
use crate::send::SendWaits;
use std::time::Duration;
use tacos_bus::BusArgs;
use tacos_shared::DroneId;
use tacos_shared::action::Action;

/// Send one action to one drone and wait for its outcome.
#[derive(Debug, Clone, clap::Args)]
pub struct SendArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Built-in scenario (city, lab) or scenario file: what the safety gate checks against.
    #[arg(long, default_value = "city")]
    pub scenario: String,
    /// Seconds to wait for the outcome.
    #[arg(long, default_value_t = 120.0)]
    pub timeout: f64,
    /// Seconds to wait for the drone to be heard before giving up on it: a drone rejoining
    /// a ground that has just (re)started takes a few seconds to reconnect.
    #[arg(long, default_value_t = 20.0)]
    pub wait_for_drone: f64,
    pub drone: String,
    #[arg(num_args = 1.., allow_hyphen_values = true)]
    pub action: Vec<String>,
}

impl SendArgs {
    pub async fn run(self) -> anyhow::Result<()> {
        let words: Vec<&str> = self.action.iter().map(String::as_str).collect();
        let action = Action::parse_words(&words).map_err(anyhow::Error::msg)?;
        let id = DroneId::new(&self.drone).map_err(|e| anyhow::anyhow!("{:?}: {e}", self.drone))?;
        let gate = SafetyGate::new(tacos_bus::load_scenario(&self.scenario)?);
        let waits = SendWaits {
            drone: Duration::from_secs_f64(self.wait_for_drone.max(0.0)),
            outcome: Duration::from_secs_f64(self.timeout.max(0.0)),
        };
        let link = GroundLink::connect(&self.bus).await?;
        // Progress on stdout, waits on stderr: scripts read the outcome from stdout.
        let say = |line: String| {
            if line.starts_with("waiting") {
                eprintln!("{line}");
            } else {
                println!("{line}");
            }
        };
        crate::send::send(&link, &gate, waits, &id, &action, say).await?;
        Ok(())
    }
}
