//! `tacos-ground replay` and `plot`: what a mission log holds, as a timeline or a picture.

use crate::mission::log::{Record, last_mission, read, timeline};
use anyhow::{Context, bail};
use std::path::PathBuf;

/// Print a mission log's timeline.
#[derive(Debug, Clone, clap::Args)]
pub struct ReplayArgs {
    pub log: PathBuf,
}

impl ReplayArgs {
    pub fn run(self) -> anyhow::Result<()> {
        let lines = read(&self.log)?;
        print!("{}", timeline(last_mission(&lines)));
        Ok(())
    }
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
        let named = lines.iter().find_map(|l| match &l.record {
            Record::MissionStart { scenario, .. } => Some(scenario.clone()),
            _ => None,
        });
        let map = self
            .map
            .or(named)
            .context("the log names no map: give --map")?;
        let scenario = tacos_bus::load_scenario(&map)?;
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
