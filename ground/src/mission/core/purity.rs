//! The core does no I/O and reads no clock: none of its files names the async runtime, the
//! middleware, the link, the log writer, the model backend (its trait and its calls; the chat
//! messages and errors of `tacos_llm` are data) or a clock (comment lines aside).

const FORBIDDEN: [&str; 14] = [
    "tokio",
    "zenoh",
    "crate::link",
    "GroundLink",
    "MissionLog",
    "LlmBackend",
    "chat_streamed",
    "Instant::now",
    "SystemTime",
    ".clock()",
    "std::fs",
    "std::net",
    "std::thread",
    "async ",
];

/// The core's own source files: `core.rs` and `core/*.rs` but the test files (`*tests.rs`,
/// `purity.rs`, `properties.rs`).
fn core_sources() -> Vec<(String, String)> {
    let dir = concat!(env!("CARGO_MANIFEST_DIR"), "/src/mission");
    let mut paths = vec![format!("{dir}/core.rs")];
    let entries = std::fs::read_dir(format!("{dir}/core")).expect("the core's folder");
    for entry in entries {
        let path = entry.expect("a folder entry").path();
        let name = path
            .file_name()
            .and_then(|n| n.to_str())
            .unwrap_or_default();
        if name.ends_with(".rs")
            && !(name.ends_with("tests.rs") || ["purity.rs", "properties.rs"].contains(&name))
        {
            paths.push(path.display().to_string());
        }
    }
    paths
        .into_iter()
        .map(|p| {
            let text = std::fs::read_to_string(&p).expect("a core source");
            (p, text)
        })
        .collect()
}

#[test]
fn the_core_names_no_runtime_middleware_link_log_writer_backend_or_clock() {
    let sources = core_sources();
    assert!(sources.len() >= 6, "the core's files: {sources:?}");
    let mut found = Vec::new();
    for (path, text) in &sources {
        for (n, line) in text.lines().enumerate() {
            if line.trim_start().starts_with("//") {
                continue;
            }
            for word in FORBIDDEN.iter().filter(|w| line.contains(*w)) {
                found.push(format!("{path}:{}: {word}", n + 1));
            }
        }
    }
    assert!(found.is_empty(), "the core must stay pure: {found:#?}");
}
