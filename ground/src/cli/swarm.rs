//! `tacos-ground swarm`: the live table of the swarm.

use crate::link::{GroundLink, GroundRole};
use std::time::Duration;
use tacos_bus::BusArgs;

#[derive(Debug, Clone, clap::Args)]
pub struct SwarmArgs {
    #[command(flatten)]
    pub bus: BusArgs,
    /// Refresh period in milliseconds.
    #[arg(long, default_value_t = 500)]
    pub period_ms: u64,
    /// Print this many tables then exit (0 = until Ctrl-C).
    #[arg(long, default_value_t = 0)]
    pub count: u64,
    /// Act as the ground station in control: beat the heartbeat that keeps the drones out
    /// of their ground-silence failsafe. A drone follows one ground station at a time, so
    /// while this beats a `send` from another process is refused (it says so). Without it
    /// the table only watches, and drones with no ground in control hold after 3 s and
    /// land after 30 s.
    #[arg(long)]
    pub in_control: bool,
}

impl SwarmArgs {
    /// Prints the table every period, until Ctrl-C or `--count` tables.
    pub async fn run(self) -> anyhow::Result<()> {
        let role = if self.in_control {
            GroundRole::InControl
        } else {
            GroundRole::Monitor
        };
        let link = GroundLink::connect_as(&self.bus, role).await?;
        let mut tick = tokio::time::interval(Duration::from_millis(self.period_ms.max(50)));
        let mut printed = 0;
        let interactive = self.count == 0;
        loop {
            tokio::select! {
                _ = super::ctrl_c() => return Ok(()),
                _ = tick.tick() => {}
            }
            let text = crate::table::render(&link.view(), link.clock().instant());
            if interactive {
                // Clear the screen and home the cursor, like `watch`.
                print!("\x1b[2J\x1b[H");
            }
            println!("swarm {}\n{text}", self.bus.swarm);
            printed += 1;
            if self.count > 0 && printed >= self.count {
                return Ok(());
            }
        }
    }
}
