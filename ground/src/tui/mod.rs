//! The pilot's terminal: a full-screen view of the swarm (map, table), the chat with the
//! models, the event log and a status bar, with an input line for instructions and direct
//! commands.
//!
//! `state` is what is shown (pure, testable), `panes` draws it, and [`run_terminal`] runs the
//! screen: it only exchanges messages with the mission, which runs in its own task, so the
//! screen stays live while a model thinks.

mod chat;
mod input_line;
mod map;
pub mod panes;
pub mod state;

#[cfg(test)]
mod tests;

pub use state::{Command, TerminalState};

use crate::link::GroundLink;
use crate::mission::{MissionUpdate, PilotInput};
use crate::task_guard::AbortOnDrop;
use crossterm::event::{Event, EventStream, KeyEventKind};
use crossterm::{cursor, execute, terminal};
use futures_util::StreamExt;
use ratatui::Terminal;
use ratatui::backend::CrosstermBackend;
use std::io::Stdout;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::{Arc, Mutex};
use std::time::Duration;
use tacos_shared::messages::TargetObservation;
use tacos_shared::scenario::Scenario;
use tokio::sync::{mpsc, watch};

/// Redraw period when nothing happens (the thinking timer and link ages move).
const FRAME: Duration = Duration::from_millis(100);

#[derive(Debug, thiserror::Error)]
pub enum TuiError {
    #[error("terminal: {0}")]
    Io(#[from] std::io::Error),
    #[error("a panic restored the terminal; the screen was closed")]
    Panicked,
}

/// True while the terminal is in raw mode on the alternate screen (restore only once).
static ACTIVE: AtomicBool = AtomicBool::new(false);
/// Set by the panic hook when it restored the terminal.
static PANICKED: AtomicBool = AtomicBool::new(false);

type PanicHook = Box<dyn Fn(&std::panic::PanicHookInfo<'_>) + Sync + Send + 'static>;

/// Leaves the alternate screen and raw mode; safe to call more than once.
fn restore_terminal() {
    if ACTIVE.swap(false, Ordering::SeqCst) {
        let _ = terminal::disable_raw_mode();
        let _ = execute!(
            std::io::stdout(),
            terminal::LeaveAlternateScreen,
            cursor::Show
        );
    }
}

/// Raw mode + alternate screen for its lifetime, and a panic hook that restores the terminal
/// before the panic message is printed. Dropping it (on every exit path) restores both.
struct TerminalGuard {
    previous_hook: Option<Arc<Mutex<Option<PanicHook>>>>,
}

impl TerminalGuard {
    fn enter() -> Result<TerminalGuard, TuiError> {
        let previous: Arc<Mutex<Option<PanicHook>>> =
            Arc::new(Mutex::new(Some(std::panic::take_hook())));
        let chained = previous.clone();
        std::panic::set_hook(Box::new(move |info| {
            if ACTIVE.load(Ordering::SeqCst) {
                PANICKED.store(true, Ordering::SeqCst);
            }
            restore_terminal();
            if let Ok(hook) = chained.lock()
                && let Some(hook) = hook.as_ref()
            {
                hook(info);
            }
        }));
        let guard = TerminalGuard {
            previous_hook: Some(previous),
        };
        PANICKED.store(false, Ordering::SeqCst);
        ACTIVE.store(true, Ordering::SeqCst);
        terminal::enable_raw_mode()?;
        execute!(std::io::stdout(), terminal::EnterAlternateScreen)?;
        Ok(guard)
    }
}

impl Drop for TerminalGuard {
    fn drop(&mut self) {
        restore_terminal();
        // Put the previous panic hook back (ours holds it; take it out first).
        if let Some(previous) = self.previous_hook.take() {
            let ours = std::panic::take_hook();
            let hook = previous.lock().ok().and_then(|mut h| h.take());
            match hook {
                Some(hook) => std::panic::set_hook(hook),
                None => std::panic::set_hook(ours),
            }
        }
    }
}

/// Runs the pilot's terminal until the pilot quits (Ctrl-C, Esc, `:q`) or the terminal fails.
///
/// The mission runs elsewhere: `updates` brings what it does, submitted lines go to `input`
/// (direct commands are carried out at once, other lines queued in a background task so the
/// screen never blocks), and `targets` brings the observed targets. The swarm is read from
/// `link` at every frame.
/// What the terminal shows of the session from the start.
pub struct Session {
    /// The model backend, as the status bar names it.
    pub backend: String,
    /// Plans are held for the pilot's approval (`--confirm`); F2 switches it.
    pub confirm: bool,
}

pub async fn run_terminal(
    link: Arc<GroundLink>,
    scenario: Scenario,
    session: Session,
    mut updates: mpsc::UnboundedReceiver<MissionUpdate>,
    input: PilotInput,
    mut targets: watch::Receiver<Vec<TargetObservation>>,
) -> Result<(), TuiError> {
    let guard = TerminalGuard::enter()?;
    let result = async {
        let mut terminal = Terminal::new(CrosstermBackend::new(std::io::stdout()))?;
        terminal.clear()?;
        event_loop(
            &mut terminal,
            &link,
            &scenario,
            session,
            &mut updates,
            &input,
            &mut targets,
        )
        .await
    }
    .await;
    drop(guard);
    result
}

async fn event_loop(
    terminal: &mut Terminal<CrosstermBackend<Stdout>>,
    link: &GroundLink,
    scenario: &Scenario,
    session: Session,
    updates: &mut mpsc::UnboundedReceiver<MissionUpdate>,
    input: &PilotInput,
    targets: &mut watch::Receiver<Vec<TargetObservation>>,
) -> Result<(), TuiError> {
    let mut state = TerminalState::new(scenario, session.backend, link.clock().instant());
    state.status.confirm = session.confirm;
    let mut keys = EventStream::new();
    let mut frame = tokio::time::interval(FRAME);
    frame.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    // Lines for the models wait here for room in the engine's queue, off the screen's loop.
    let (outbox, mut queued) = mpsc::unbounded_channel::<String>();
    let forward = input.clone();
    let forwarder = tokio::spawn(async move {
        while let Some(line) = queued.recv().await {
            if forward.submit(&line).await.is_err() {
                break;
            }
        }
    });
    // The forwarder stops when the terminal closes.
    let _stop_forwarder = AbortOnDrop(forwarder);
    let (mut updates_open, mut targets_open) = (true, true);
    loop {
        tokio::select! {
            _ = frame.tick() => {}
            update = updates.recv(), if updates_open => match update {
                Some(update) => {
                    let now = link.clock().instant();
                    state.apply_update(&update, now);
                    // Take a burst in one frame.
                    while let Ok(update) = updates.try_recv() {
                        state.apply_update(&update, now);
                    }
                }
                None => {
                    updates_open = false;
                    state.log(state::EventKind::Error, "the mission stopped; nothing typed here reaches the swarm");
                }
            },
            changed = targets.changed(), if targets_open => {
                if changed.is_err() {
                    targets_open = false;
                }
            }
            event = keys.next() => match event {
                Some(Ok(Event::Key(key))) if key.kind != KeyEventKind::Release => {
                    match state.key(key) {
                        Some(Command::Quit) => return Ok(()),
                        Some(Command::Submit(line)) => {
                            if input.is_closed() {
                                state.log(state::EventKind::Error, format!("not sent (the mission stopped): {line}"));
                            } else if input.directive(&line).is_some() {
                                // Gate check and a zenoh put per drone: immediate, and never
                                // behind lines waiting for the models.
                                if input.submit(&line).await.is_err() {
                                    state.log(state::EventKind::Error, format!("not sent (the mission stopped): {line}"));
                                }
                            } else if outbox.send(line).is_err() {
                                state.log(state::EventKind::Error, "the mission no longer takes lines");
                            }
                        }
                        None => {}
                    }
                }
                Some(Ok(_)) => {}
                Some(Err(e)) => return Err(TuiError::Io(e)),
                None => return Ok(()),
            },
        }
        if PANICKED.load(Ordering::SeqCst) {
            return Err(TuiError::Panicked);
        }
        let now = link.clock().instant();
        {
            let view = link.view();
            state.refresh_swarm(&view, now);
        }
        let observed = targets.borrow_and_update().clone();
        state.set_targets(&observed);
        terminal.draw(|f| panes::draw(f, &state))?;
    }
}
