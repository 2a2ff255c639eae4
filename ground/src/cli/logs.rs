//! `tacos-ground replay` and `plot`: what a mission log holds, as a timeline or a picture.

use crate::mission::log::{Line, Record, last_mission, read, read_checked, timeline};
use crate::mission::replay::replay;
use crate::safety::SafetyGate;
use anyhow::{Context, bail};
use std::path::PathBuf;

/// Print a mission log's timeline; with --check, feed its traced steps to a fresh core.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    pub log: PathBuf,
    /// Feed the mission's traced steps (it ran with --trace-steps) to a fresh mission core
    /// and compare what it sends with what the log says was sent; exits 1 when they differ.
    #[arg(long)]
    pub check: bool,
    /// The map, when not the one the log names (city, lab or a scenario file).
    #[arg(long)]
    pub map: Option<String>,
}

impl ReplayArgs {
    pub fn run(self) -> anyhow::Result<()> {
        if !self.check {
            let lines = read(&self.log)?;
            print!("{}", timeline(last_mission(&lines)));
            return Ok(());
        }
        // Every line counts: a step skipped would make the replay differ for no fault of it.
        let contents = read_checked(&self.log)?;
        if let Some(s) = contents.skipped.first() {
            bail!(
                "{} line {} cannot be read ({}): a replay needs every step",
                self.log.display(),
                s.line,
                s.reason
            );
        }
        let lines = last_mission(&contents.records);
        let scenario = tacos_bus::load_scenario(&map_of(lines, self.map)?)?;
        let replayed = replay(lines, &SafetyGate::new(scenario))?;
        if let Some(difference) = replayed.first_difference() {
            bail!(
                "replayed {} steps: the core decided differently from the log: {difference}",
                replayed.steps
            );
        }
        println!(
            "replayed {} steps into a fresh core: {} sends, the same as the log's \
             (drone, action, task and sequence number)",
            replayed.steps,
            replayed.replayed.len()
        );
        Ok(())
    }
}

/// The map given, or else the one the mission's log names.
fn map_of(lines: &[Line], given: Option<String>) -> anyhow::Result<String> {
    let named = lines.iter().find_map(|l| match &l.record {
        Record::MissionStart { scenario, .. } => Some(scenario.clone()),
        _ => None,
    });
    given.or(named).context("the log names no map: give --map")
}

/// Draw a mission's trajectories over the map, coloured by speed (SVG).
#[derive(Debug, Clone, clap::Args)]
pub struct PlotArgs {
    pub log: PathBuf,
    /// Output file: .svg, or .png (the same picture rasterised at twice its size).
    #[arg(short, long, default_value = "mission.svg")]
    pub output: PathBuf,
    /// The map, when not the one the log names (city, lab or a scenario file).
    #[arg(long)]
    pub map: Option<String>,
}

impl PlotArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let all = read(&self.log)?;
        let lines = last_mission(&all);
        let scenario = tacos_bus::load_scenario(&map_of(lines, self.map)?)?;
        let svg = crate::plot::svg(lines, &scenario);
        let bytes = match self.output.extension().and_then(|e| e.to_str()) {
            Some("svg") => svg.into_bytes(),
            Some("png") => crate::plot::png(&svg, 2.0)?,
            _ => bail!("name the output *.svg or *.png"),
        };
        std::fs::write(&self.output, bytes)
            .with_context(|| format!("writing {}", self.output.display()))?;
        println!("wrote {}", self.output.display());
        Ok(())
    }
}
