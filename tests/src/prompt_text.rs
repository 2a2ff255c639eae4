//! Reading the engine's requests the way the stand-in models of the tests do: the sections of a
//! rendered prompt (`## Title`), its plan lines and its swarm lines, and the request itself.

/// The engine's rendered request in `request`: its last user message that starts with a section
/// (a repair round's "Your reply was rejected" comes after it).
pub fn request_text(request: &tacos_llm::ChatRequest) -> &str {
    request
        .messages
        .iter()
        .rev()
        .find(|m| m.role == tacos_llm::Role::User && m.content.starts_with("## "))
        .map_or("", |m| m.content.as_str())
}

/// The body of the `## title` section of `text`, up to the next section; empty if there is none.
pub fn section<'a>(text: &'a str, title: &str) -> &'a str {
    let Some(start) = text.find(&format!("## {title}\n")) else {
        return "";
    };
    let rest = &text[start + title.len() + 4..];
    &rest[..rest.find("\n## ").unwrap_or(rest.len())]
}

/// One plan line, `- T4 alfa goto(car_11): not started`.
pub type PlanLine = (String, String, String, String, String);

/// The lines of the "Plan" (Supervisor) and "Pending plan" (Coordinator) sections as (task,
/// drone, action, target, status); an action without argument has target "none". A pending
/// plan's line holds its status; a Supervisor's plan line is the call alone, and the status
/// is in "Your memory for this plan" (`- T1: running, after 1 failure`; a task not listed
/// there is not started).
pub fn plan_lines(text: &str) -> Vec<PlanLine> {
    let memory = section(text, "Your memory for this plan");
    let status_of = |task: &str| {
        memory
            .lines()
            .find_map(|l| l.strip_prefix(&format!("- {task}: ")))
            // "running, after 1 failure": the status alone.
            .map_or("not started", |s| s.split(", after ").next().unwrap_or(s))
            .to_owned()
    };
    section(text, "Plan")
        .lines()
        .chain(section(text, "Pending plan").lines())
        .filter_map(|l| {
            let line = l.strip_prefix("- ")?;
            let (call, status) = match line.rsplit_once("): ") {
                Some((call, status)) => (call, Some(status.to_owned())),
                None => (line.strip_suffix(')')?, None),
            };
            let mut words = call.splitn(3, ' ');
            let (task, drone, rest) = (words.next()?, words.next()?, words.next()?);
            let (action, target) = rest.split_once('(')?;
            let target = if target.is_empty() { "none" } else { target };
            Some((
                task.into(),
                drone.into(),
                action.into(),
                target.into(),
                status.unwrap_or_else(|| status_of(task)),
            ))
        })
        .collect()
}

/// One swarm line, `- alfa: flying at (…); last action T1 arm_takeoff(): done`, as (drone, mode
/// (the first word after the name), busy (its action is running), everything after the name).
pub type SwarmLine = (String, String, bool, String);

/// The lines of the "Swarm state" section.
pub fn swarm_lines(text: &str) -> Vec<SwarmLine> {
    section(text, "Swarm state")
        .lines()
        .filter_map(|l| {
            let (drone, rest) = l.strip_prefix("- ")?.split_once(": ")?;
            let mode = rest.split(' ').next()?.to_owned();
            Some((
                drone.to_owned(),
                mode,
                rest.contains("running"),
                rest.to_owned(),
            ))
        })
        .collect()
}

/// A chat-completions body as a served stand-in model reads it (`chat_server`): its system
/// message and the engine's rendered request (as [`request_text`]); `None` without a request.
pub fn body_text(body: &serde_json::Value) -> Option<(String, String)> {
    let messages = body["messages"].as_array()?;
    let text = |m: &serde_json::Value| m["content"].as_str().unwrap_or_default().to_owned();
    let system = messages.first().map(text).unwrap_or_default();
    let request = messages
        .iter()
        .rev()
        .map(text)
        .find(|t| t.starts_with("## "))?;
    Some((system, request))
}

/// What a stand-in Supervisor starts: for each drone, the first call the engine's schema offers
/// it (`/properties/actions/items/anyOf`), as the `actions` of a reply.
pub fn first_offered_per_drone(request: &tacos_llm::ChatRequest) -> Vec<serde_json::Value> {
    first_offered_in(request.schema.as_ref().map(|s| &s.schema))
}

/// [`first_offered_per_drone`] for a served model: the schema is the body's `response_format`.
pub fn first_offered_in_body(body: &serde_json::Value) -> Vec<serde_json::Value> {
    first_offered_in(body["response_format"].pointer("/json_schema/schema"))
}

fn first_offered_in(schema: Option<&serde_json::Value>) -> Vec<serde_json::Value> {
    let offered: Vec<serde_json::Value> = schema
        .and_then(|s| s.pointer("/properties/actions/items/anyOf"))
        .and_then(serde_json::Value::as_array)
        .cloned()
        .unwrap_or_default();
    let first = |alt: &serde_json::Value, field: &str| alt["properties"][field]["enum"][0].clone();
    let mut actions: Vec<serde_json::Value> = Vec::new();
    for alt in &offered {
        if !actions.iter().any(|a| a["drone"] == first(alt, "drone")) {
            actions.push(serde_json::json!({
                "task": first(alt, "task"), "drone": first(alt, "drone"),
                "action": first(alt, "action"), "target": first(alt, "target"), "xyz": null
            }));
        }
    }
    actions
}
