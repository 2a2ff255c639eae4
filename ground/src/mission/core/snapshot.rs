//! One step's view of the world, taken once by the engine so every decision of the step sees
//! the same swarm: the view as the link had it, the targets seen, the time, and this ground
//! station's epoch.

use crate::swarm::SwarmView;
use std::time::Instant;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::Scenario;

#[derive(Debug, Clone)]
pub(crate) struct Snapshot {
    pub(crate) swarm: SwarmView,
    /// The targets seen that the scenario has (`untrusted::known_targets`).
    pub(crate) targets: Vec<TargetObservation>,
    /// The swarm clock's time of the step.
    pub(crate) now: Instant,
    /// This ground station's epoch: a drone that reports another takes none of our actions.
    pub(crate) ground: u64,
}

impl Snapshot {
    /// The scenario's drones the view has heard of, in the scenario's order.
    pub(crate) fn swarm_ids(&self, scenario: &Scenario) -> Vec<String> {
        scenario
            .drones
            .iter()
            .filter(|d| self.swarm.get(&d.id).is_some())
            .map(|d| d.id.to_string())
            .collect()
    }
}
