//! A world event from the network (a detection, an injected fault) taken into the mission: only
//! when every name in it is the map's (`untrusted::checked_event`); then it is logged, told,
//! kept for the prompts' world section and remembered where the layers read it (the
//! Coordinator's history, or the monolithic model's record of what happened).

use super::book::PlanBook;
use super::effect::Effect;
use crate::mission::config::Mode;
use crate::mission::log::Record;
use crate::mission::report::{EventTopic, MissionUpdate};
use crate::mission::untrusted;
use tacos_prompts::render::HistoryEntry;
use tacos_shared::messages::WorldEvent;
use tacos_shared::scenario::Scenario;

/// Takes in `event`; `events` are the world's events as the prompts show them. True when it
/// was taken in (a cycle is then due); an event naming something the map lacks is logged and
/// left out of every prompt.
pub(crate) fn world_event(
    event: WorldEvent,
    scenario: &Scenario,
    mode: Mode,
    book: &mut PlanBook,
    events: &mut Vec<String>,
) -> (bool, Vec<Effect>) {
    let event = match untrusted::checked_event(event, scenario) {
        Ok(event) => event,
        Err(why) => {
            let text = format!("world event ignored: {why}");
            return (false, vec![Effect::Note(Record::Event { text })]);
        }
    };
    let text = event.to_string();
    events.push(text.clone());
    let topic = match &event {
        WorldEvent::Detection { .. } => EventTopic::Detection,
        WorldEvent::FaultInjected { .. } => EventTopic::Failure,
    };
    let mut effects = vec![
        Effect::Note(Record::WorldEvent { text: text.clone() }),
        Effect::Tell(MissionUpdate::Event {
            topic,
            text: text.clone(),
        }),
    ];
    match mode {
        Mode::Mnl => book.mnl.executed.push(format!("event: {text}")),
        Mode::Tacos | Mode::Wor => effects.push(Effect::Remember(HistoryEntry::Event(text))),
    }
    (true, effects)
}
