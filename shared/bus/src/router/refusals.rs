//! Counting what the router's access control refuses. zenoh drops a denied message without a
//! word to anyone; the one place it states a decision is a TRACE event of its access-control
//! interceptor. [`RefusalCounter`] is a `tracing` layer that reads those events and keeps, per
//! principal, kind of message and key, how many were refused on the way in, for `tacos-router`
//! to report. The event text is zenoh's (the pinned version); [`parse`] is tested on it, and
//! `tests/tests/multi_host.rs` fails should a zenoh upgrade change it.

use std::collections::{BTreeMap, HashMap};
use std::sync::{Arc, Mutex, PoisonError};
use tracing::field::{Field, Visit};
use tracing_subscriber::Layer;
use tracing_subscriber::filter::{Filtered, Targets};
use tracing_subscriber::layer::Context;

/// The module whose events carry zenoh's access-control decisions.
pub const ACL_TARGET: &str = "zenoh::net::routing::interceptor::access_control";

/// One refusal as zenoh states it.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Denial {
    /// The zenoh id of the refused session.
    pub zid: String,
    /// The ACL subject it matched (certificate name, link, ...), when zenoh names it: it does
    /// on a key's first refusal, not on the cached ones after.
    pub subject: Option<String>,
    /// zenoh's name of the message, e.g. "Put (ingress)".
    pub what: String,
    pub key: String,
}

impl Denial {
    /// Refused on its way *into* the router (sent by that session), not held back from it.
    pub fn inbound(&self) -> bool {
        self.what.ends_with("(ingress)")
    }
}

/// Reads one access-control event's text; `None` for anything but a refusal.
pub fn parse(text: &str) -> Option<Denial> {
    match decision(text)? {
        (false, denial) => Some(denial),
        (true, _) => None,
    }
}

/// A decision's text: whether it allowed, and on what.
fn decision(text: &str) -> Option<(bool, Denial)> {
    let (allowed, (who, rest)) = match text.split_once(" is unauthorized to ") {
        Some(parts) => (false, parts),
        None => (true, text.split_once(" is authorized to ")?),
    };
    let (what, key) = rest.rsplit_once(" on ")?;
    let who = who.strip_prefix("Using cached result: ").unwrap_or(who);
    let (zid, subject) = match who.split_once(" on ") {
        Some((zid, subject)) => (zid, Some(subject.to_owned())),
        None => (who, None),
    };
    // An undeclaration names its key as `Some(key)` / `None`.
    let key = key
        .strip_prefix("Some(")
        .and_then(|k| k.strip_suffix(')'))
        .unwrap_or(key);
    Some((
        allowed,
        Denial {
            zid: zid.to_owned(),
            subject,
            what: what.to_owned(),
            key: key.to_owned(),
        },
    ))
}

/// The certificate name in a zenoh subject such as
/// `Interface(eth0)+CertCommonName(alfa)+Transport(Tls)+<zid>`.
fn common_name(subject: &str) -> Option<&str> {
    let rest = subject.split_once("CertCommonName(")?.1;
    Some(rest.split_once(')')?.0)
}

/// Refusals counted so far: (principal, what, key) → how many.
pub type Counts = BTreeMap<(String, String, String), u64>;

#[derive(Default)]
struct State {
    counts: Counts,
    /// zenoh id → the subject it was named with (cached refusals name only the id).
    subjects: HashMap<String, String>,
}

/// Counts the refusals of the router's access control (install its [`RefusalCounter::layer`]).
#[derive(Clone, Default)]
pub struct RefusalCounter {
    state: Arc<Mutex<State>>,
}

impl RefusalCounter {
    /// The layer to add to the process's `tracing` subscriber: it sees zenoh's access-control
    /// events at TRACE whatever the log filter says, and nothing else.
    pub fn layer<S>(&self) -> Filtered<CountingLayer, Targets, S>
    where
        S: tracing::Subscriber + for<'a> tracing_subscriber::registry::LookupSpan<'a>,
    {
        CountingLayer {
            counter: self.clone(),
        }
        .with_filter(Targets::new().with_target(ACL_TARGET, tracing::Level::TRACE))
    }

    /// Remembers the principal a decision names its session by (cached ones name only the id).
    fn learn_name(&self, decision: &Denial) {
        if let Some(subject) = &decision.subject {
            let name = common_name(subject).unwrap_or(subject).to_owned();
            let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
            if state.subjects.get(&decision.zid) != Some(&name) {
                state.subjects.insert(decision.zid.clone(), name);
            }
        }
    }

    /// Adds one event's refusal, if it is an inbound one.
    pub fn record(&self, denial: Denial) {
        if !denial.inbound() {
            return;
        }
        let mut state = self.state.lock().unwrap_or_else(PoisonError::into_inner);
        let principal = match &denial.subject {
            Some(subject) => {
                let name = common_name(subject).unwrap_or(subject).to_owned();
                state.subjects.insert(denial.zid.clone(), name.clone());
                name
            }
            None => state
                .subjects
                .get(&denial.zid)
                .cloned()
                .unwrap_or_else(|| denial.zid.clone()),
        };
        *state
            .counts
            .entry((principal, denial.what, denial.key))
            .or_default() += 1;
    }

    pub fn counts(&self) -> Counts {
        self.state
            .lock()
            .unwrap_or_else(PoisonError::into_inner)
            .counts
            .clone()
    }
}

/// The `tracing` layer of a [`RefusalCounter`].
pub struct CountingLayer {
    counter: RefusalCounter,
}

/// The permissions zenoh is working out on this thread: a key, and the position in
/// [`CACHED_KINDS`] of the next kind it will decide.
struct Caching {
    key: String,
    next: usize,
}

thread_local! {
    static CACHING: std::cell::RefCell<Option<Caching>> = const { std::cell::RefCell::new(None) };
}

/// The kinds of message zenoh decides when it caches a key's permissions (its
/// `compute_keyexpr_cache`, ingress and egress alike), in its order: each once per subject the
/// session was authenticated as (until one allows), none at all for a session with no subject.
const CACHED_KINDS: [&str; 9] = [
    "Query",
    "Reply",
    "Put",
    "Delete",
    "Declare/Undeclare Subscriber",
    "Declare/Undeclare Queryable",
    "Declare/Undeclare Liveliness Token",
    "Liveliness Query",
    "Declare Liveliness Subscriber",
];

/// The key of zenoh's "ACL (ingress): caching permissions for `KEY` ..." event.
fn caching_key(text: &str) -> Option<&str> {
    let rest = text.split_once("caching permissions for `")?.1;
    Some(rest.split_once('`')?.0)
}

/// Whether a decision is one of those zenoh works out while caching a key (not one on a
/// message), consuming it if so. They follow the caching event at once, on its thread, in
/// [`CACHED_KINDS`]' order: anything out of that order (a session with no subject logs none of
/// them, and its key's next real refusal may come on the same thread) ends the caching and is a
/// decision on a message.
fn part_of_caching(decision: &Denial) -> bool {
    if decision.subject.is_none() {
        // A cached result: the caching, if any, is over.
        CACHING.with(|c| *c.borrow_mut() = None);
        return false;
    }
    let kind = decision
        .what
        .rsplit_once(" (")
        .map_or(decision.what.as_str(), |(kind, _)| kind);
    CACHING.with(|c| {
        let mut c = c.borrow_mut();
        let Some(caching) = c.as_mut().filter(|c| c.key == decision.key) else {
            *c = None;
            return false;
        };
        let same_as_last = caching.next > 0 && CACHED_KINDS[caching.next - 1] == kind;
        if same_as_last {
            return true;
        }
        if CACHED_KINDS.get(caching.next) == Some(&kind) {
            caching.next += 1;
            return true;
        }
        *c = None;
        false
    })
}

impl<S: tracing::Subscriber> Layer<S> for CountingLayer {
    fn on_event(&self, event: &tracing::Event<'_>, _ctx: Context<'_, S>) {
        let mut text = MessageText(String::new());
        event.record(&mut text);
        // The first message on a key makes zenoh work out every permission on it, each stated
        // like a decision; the message's own decision follows as a cached one. Those nine are
        // not decisions on anything sent.
        if let Some(key) = caching_key(&text.0) {
            CACHING.with(|c| {
                *c.borrow_mut() = Some(Caching {
                    key: key.to_owned(),
                    next: 0,
                })
            });
            return;
        }
        if let Some((allowed, decision)) = decision(&text.0) {
            self.counter.learn_name(&decision);
            // Every decision moves the caching on, the allowed ones too.
            let caching = part_of_caching(&decision);
            if !allowed && !caching {
                self.counter.record(decision);
            }
        }
    }
}

struct MessageText(String);

impl Visit for MessageText {
    fn record_debug(&mut self, field: &Field, value: &dyn std::fmt::Debug) {
        if field.name() == "message" {
            self.0 = format!("{value:?}");
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn reads_zenohs_refusals_first_named_then_cached() {
        let first = parse(
            "6e9f4a1 on alfa is unauthorized to Put (ingress) on tacos/default/drone/bravo/action",
        );
        assert_eq!(
            first,
            Some(Denial {
                zid: "6e9f4a1".into(),
                subject: Some("alfa".into()),
                what: "Put (ingress)".into(),
                key: "tacos/default/drone/bravo/action".into(),
            })
        );
        let cached = parse(
            "Using cached result: 6e9f4a1 is unauthorized to Put (ingress) on tacos/default/ground/heartbeat",
        )
        .expect("a cached refusal");
        assert_eq!(cached.subject, None);
        assert_eq!(cached.key, "tacos/default/ground/heartbeat");
        let undeclare = parse(
            "Using cached result: 6e9f4a1 is unauthorized to Undeclare Subscriber (ingress) on Some(tacos/x)",
        )
        .expect("an undeclaration");
        assert_eq!(undeclare.key, "tacos/x");
        assert_eq!(
            parse(
                "6e9f4a1 on alfa is authorized to Put (ingress) on tacos/default/drone/alfa/status"
            ),
            None
        );
    }

    #[test]
    fn a_subject_is_named_by_its_certificate() {
        assert_eq!(
            common_name("Interface(eth0)+CertCommonName(alfa)+Transport(Tls)+2a85b8"),
            Some("alfa")
        );
        assert_eq!(common_name("Interface(eth0)+2a85b8"), None);
        assert_eq!(
            caching_key("ACL (ingress): caching permissions for `tacos/s/ground/heartbeat` ..."),
            Some("tacos/s/ground/heartbeat")
        );
    }

    #[test]
    fn counts_inbound_refusals_per_principal_naming_cached_ones_by_their_first() {
        let counter = RefusalCounter::default();
        for text in [
            "z1 on Interface(eth0)+CertCommonName(alfa)+z1 is unauthorized to Put (ingress) on k/bravo/action",
            "Using cached result: z1 is unauthorized to Put (ingress) on k/bravo/action",
            "Using cached result: z1 is unauthorized to Put (ingress) on k/bravo/action",
            // Held back from alfa, not sent by it: not a refusal of alfa's.
            "z1 on alfa is unauthorized to Put (egress) on k/bravo/status",
            "Using cached result: z9 is unauthorized to Put (ingress) on k/x",
        ] {
            counter.record(parse(text).expect("a refusal"));
        }
        let counts = counter.counts();
        let key = |p: &str, k: &str| (p.to_owned(), "Put (ingress)".to_owned(), k.to_owned());
        assert_eq!(counts.get(&key("alfa", "k/bravo/action")), Some(&3));
        assert_eq!(counts.get(&key("z9", "k/x")), Some(&1));
        assert_eq!(counts.len(), 2);
    }

    const KEY: &str = "tacos/s/world/targets";
    const SUBJECT: &str = "z1 on Interface(eth0)+CertCommonName(alfa)+z1";

    /// States `text` as zenoh's access-control interceptor does.
    fn say(text: String) {
        tracing::trace!(target: ACL_TARGET, "{text}");
    }

    /// What a counter's layer counted of the events `emit` states, and how many of alfa's puts
    /// on [`KEY`] it counted.
    fn counted(emit: impl FnOnce()) -> (Counts, Option<u64>) {
        use tracing_subscriber::prelude::*;
        let counter = RefusalCounter::default();
        let subscriber = tracing_subscriber::registry().with(counter.layer());
        tracing::subscriber::with_default(subscriber, emit);
        let counts = counter.counts();
        let puts = (
            "alfa".to_owned(),
            "Put (ingress)".to_owned(),
            KEY.to_owned(),
        );
        let alfa_puts = counts.get(&puts).copied();
        (counts, alfa_puts)
    }

    #[test]
    fn the_decisions_zenoh_works_out_while_caching_a_key_are_not_counted() {
        let (counts, alfa_puts) = counted(|| {
            say(format!(
                "ACL (ingress): caching permissions for `{KEY}` ..."
            ));
            for kind in CACHED_KINDS {
                say(format!(
                    "{SUBJECT} is unauthorized to {kind} (ingress) on {KEY}"
                ));
            }
            // The message's own decision, from the cache; then one decided without it.
            say(format!(
                "Using cached result: z1 is unauthorized to Put (ingress) on {KEY}"
            ));
            say(format!(
                "{SUBJECT} is unauthorized to Put (ingress) on {KEY}"
            ));
            // Another module's event is not read.
            tracing::trace!(target: "elsewhere", "{SUBJECT} is unauthorized to Put (ingress) on {KEY}");
        });
        assert_eq!(alfa_puts, Some(2), "{counts:?}");
        assert_eq!(counts.len(), 1, "{counts:?}");
    }

    /// Seen in CI: the router cached `world/targets` for a session with no subject (nothing
    /// decided), and alfa's next refused put on that thread was taken for part of the caching,
    /// so 19 of 20 were counted.
    #[test]
    fn a_refusal_after_a_caching_that_decided_nothing_is_counted() {
        let (counts, alfa_puts) = counted(|| {
            say(format!("ACL (egress): caching permissions for `{KEY}` ..."));
            say(format!(
                "{SUBJECT} is unauthorized to Put (ingress) on {KEY}"
            ));
            // Two subjects denying: each kind stated twice, none of it counted.
            say(format!(
                "ACL (ingress): caching permissions for `{KEY}` ..."
            ));
            for kind in CACHED_KINDS {
                for _ in 0..2 {
                    say(format!(
                        "{SUBJECT} is unauthorized to {kind} (ingress) on {KEY}"
                    ));
                }
            }
            say(format!(
                "{SUBJECT} is unauthorized to Put (ingress) on {KEY}"
            ));
        });
        assert_eq!(alfa_puts, Some(2), "{counts:?}");
    }

    /// Seen in CI: a caching that allows some kinds (alfa may put and declare a token on its own
    /// key) and denies the rest had every refusal after its first allowed kind counted.
    #[test]
    fn a_caching_that_allows_some_kinds_is_not_counted() {
        let (counts, alfa_puts) = counted(|| {
            say(format!(
                "ACL (ingress): caching permissions for `{KEY}` ..."
            ));
            for kind in CACHED_KINDS {
                let verdict = if kind == "Put" || kind == "Declare/Undeclare Liveliness Token" {
                    "authorized"
                } else {
                    "unauthorized"
                };
                say(format!(
                    "{SUBJECT} is {verdict} to {kind} (ingress) on {KEY}"
                ));
            }
            say(format!(
                "Using cached result: z1 is unauthorized to Delete (ingress) on {KEY}"
            ));
        });
        assert_eq!(alfa_puts, None, "{counts:?}");
        let deletes = (
            "alfa".to_owned(),
            "Delete (ingress)".to_owned(),
            KEY.to_owned(),
        );
        assert_eq!(counts.get(&deletes), Some(&1), "{counts:?}");
        assert_eq!(counts.len(), 1, "{counts:?}");
    }
}
