//! The panes rendered on ratatui's `TestBackend` from one fixed state (three drones of the lab
//! scenario, a plan, two Supervisor cycles, events, a call in flight), compared with the
//! expected screens (`screens.rs`); the state's own rules are in `state.rs`.

use super::panes::{self, DRONE_MARKER};
use super::state::{ChatEntry, Command, EventKind, Focus, TRAIL_SPAN, TRAIL_STEP, TerminalState};
use crate::mission::log::RefusedBy;
use crate::mission::{EventTopic, MissionUpdate};
use crate::swarm::SwarmView;
use crossterm::event::{KeyCode, KeyEvent, KeyModifiers};
use ratatui::Terminal;
use ratatui::backend::TestBackend;
use ratatui::buffer::Buffer;
use ratatui::layout::Rect;
use ratatui::style::Color;
use std::time::{Duration, Instant};
use tacos_shared::action::Action;
use tacos_shared::messages::{
    ActionProgress, ActionState, DroneStatus, FailureReason, TargetObservation,
};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, DroneMode, Vec3};

mod screens;
mod state;

use screens::*;

fn at(t0: Instant, secs: f64) -> Instant {
    t0 + Duration::from_secs_f64(secs)
}

fn lab() -> Scenario {
    Scenario::builtin("lab").expect("the lab scenario is built in")
}

fn status(
    id: &str,
    mode: DroneMode,
    position: [f64; 3],
    velocity: [f64; 3],
    action: Option<ActionProgress>,
) -> DroneStatus {
    DroneStatus {
        drone: DroneId::new(id).expect("valid id"),
        counter: 1,
        mode,
        armed: mode.is_airborne(),
        position: Vec3::from(position),
        velocity: Vec3::from(velocity),
        autopilot_link: true,
        action,
        failsafe: None,
        peers_silent: false,
        malformed_actions: 0,
        ground: None,
        refused: None,
        autopilot_took_over: None,
    }
}

fn typed(state: &mut TerminalState, text: &str) {
    for c in text.chars() {
        assert_eq!(state.key(key(KeyCode::Char(c))), None);
    }
}

fn key(code: KeyCode) -> KeyEvent {
    KeyEvent::new(code, KeyModifiers::NONE)
}

fn ctrl(c: char) -> KeyEvent {
    KeyEvent::new(KeyCode::Char(c), KeyModifiers::CONTROL)
}

/// The fixed state every pane test renders: t0 + 12 s into a search for the dog.
fn fixed_state() -> TerminalState {
    let t0 = Instant::now();
    let now = at(t0, 12.0);
    let mut state = TerminalState::new(&lab(), "embedded qwen2.5-0.5b (offline)", t0);

    // The pilot's line, typed.
    typed(&mut state, "find the dog in the small park");
    assert_eq!(
        state.key(key(KeyCode::Enter)),
        Some(Command::Submit("find the dog in the small park".into()))
    );

    let updates: Vec<(f64, MissionUpdate)> = vec![
        (
            0.5,
            MissionUpdate::Thinking {
                layer: "coordinator",
            },
        ),
        (
            3.7,
            MissionUpdate::Call {
                layer: "coordinator",
                latency: Duration::from_millis(3200),
                prompt_tokens: 1840,
                completion_tokens: 212,
            },
        ),
        (
            3.7,
            MissionUpdate::Plan {
                reasoning: "The dog hides in the small park. alfa is closest: it takes off and \
                            searches there; bravo stays on the ground as a reserve."
                    .into(),
                calls: vec![
                    "t1 alfa arm_takeoff()".into(),
                    "t2 alfa goto(small_park)".into(),
                ],
            },
        ),
        (
            3.8,
            MissionUpdate::Thinking {
                layer: "supervisor",
            },
        ),
        (
            4.9,
            MissionUpdate::Call {
                layer: "supervisor",
                latency: Duration::from_millis(1100),
                prompt_tokens: 1322,
                completion_tokens: 64,
            },
        ),
        (
            4.9,
            MissionUpdate::Sent {
                drone: "alfa".into(),
                action: "arm_takeoff()".into(),
                seq: 1_700_000_000_012_345,
            },
        ),
        (
            4.9,
            MissionUpdate::Cycle {
                plan_cycle: 1,
                reasoning: "alfa is idle: start t1.".into(),
                actions: vec!["t1 alfa arm_takeoff()".into()],
            },
        ),
        (
            7.5,
            MissionUpdate::Outcome {
                drone: "alfa".into(),
                action: "t1 alfa arm_takeoff()".into(),
                outcome: "done".into(),
                failed: false,
            },
        ),
        (
            7.6,
            MissionUpdate::Event {
                topic: EventTopic::Failure,
                text: "charlie became unavailable".into(),
            },
        ),
        (
            7.6,
            MissionUpdate::Thinking {
                layer: "supervisor",
            },
        ),
        (
            8.4,
            MissionUpdate::Call {
                layer: "supervisor",
                latency: Duration::from_millis(800),
                prompt_tokens: 1405,
                completion_tokens: 71,
            },
        ),
        (
            8.4,
            MissionUpdate::Rejected {
                layer: "supervisor",
                refusal: "t3 charlie arm_takeoff(): charlie is unavailable".into(),
                by: RefusedBy::Checks,
            },
        ),
        (
            8.8,
            MissionUpdate::Call {
                layer: "supervisor",
                latency: Duration::from_millis(400),
                prompt_tokens: 1530,
                completion_tokens: 58,
            },
        ),
        (
            8.8,
            MissionUpdate::Sent {
                drone: "alfa".into(),
                action: "goto(-2.5, 2.5, 1.0)".into(),
                seq: 1_700_000_000_012_346,
            },
        ),
        (
            8.8,
            MissionUpdate::Cycle {
                plan_cycle: 2,
                reasoning: "t1 done; alfa flies to the small park (t2).".into(),
                actions: vec!["t2 alfa goto(small_park)".into()],
            },
        ),
        (
            8.8,
            MissionUpdate::Thinking {
                layer: "supervisor",
            },
        ),
    ];
    for (secs, update) in &updates {
        state.apply_update(update, at(t0, *secs));
    }

    // alfa's trail so far: climbing out from its home towards the park.
    for (i, (x, y)) in [(-1.0, -3.5), (-1.0, -2.5), (-1.0, -1.5), (-1.0, -0.5)]
        .into_iter()
        .enumerate()
    {
        state.add_trail_point("alfa", Vec3::new(x, y, 1.0), at(t0, 8.0 + i as f64));
    }

    let mut view = SwarmView::default();
    view.apply_status(
        status(
            "alfa",
            DroneMode::Flying,
            [-1.0, 0.5, 1.0],
            [-0.3, 0.4, 0.0],
            Some(ActionProgress {
                seq: 1_700_000_000_012_346,
                task_id: Some("t2".into()),
                action: Action::Goto {
                    target: Vec3::new(-2.5, 2.5, 1.0),
                },
                state: ActionState::Running { progress: 0.4 },
            }),
        ),
        at(t0, 11.95),
    );
    view.apply_status(
        status("bravo", DroneMode::Idle, [0.0, -3.5, 0.0], [0.0; 3], None),
        at(t0, 11.88),
    );
    view.apply_status(
        status(
            "charlie",
            DroneMode::Flying,
            [1.5, -1.0, 1.0],
            [0.0; 3],
            Some(ActionProgress {
                seq: 1_700_000_000_012_300,
                task_id: None,
                action: Action::Hold,
                state: ActionState::Failed(FailureReason::AutopilotLinkLost),
            }),
        ),
        at(t0, 9.5),
    );
    state.refresh_swarm(&view, now);
    state.set_targets(&[TargetObservation {
        name: "dog".into(),
        position: Vec3::new(-2.4, 2.6, 0.0),
        velocity: Vec3::zeros(),
    }]);
    state
}

/// The text of a buffer, one string per row.
fn text(buf: &Buffer) -> Vec<String> {
    let area = buf.area;
    (area.top()..area.bottom())
        .map(|y| {
            (area.left()..area.right())
                .map(|x| buf[(x, y)].symbol())
                .collect::<String>()
        })
        .collect()
}

fn render(width: u16, height: u16, pane: impl Fn(&TerminalState, Rect, &mut Buffer)) -> Buffer {
    let state = fixed_state();
    let area = Rect::new(0, 0, width, height);
    let mut buf = Buffer::empty(area);
    pane(&state, area, &mut buf);
    buf
}

fn assert_screen(buf: &Buffer, expected: &[&str]) {
    let got = text(buf);
    if got != expected {
        let shown: Vec<String> = got.iter().map(|l| format!("    \"{l}\",")).collect();
        panic!("the screen differs; it was:\n{}", shown.join("\n"));
    }
}

/// Where a string starts on the screen.
fn find(buf: &Buffer, needle: &str) -> Option<(u16, u16)> {
    let rows = text(buf);
    rows.iter().enumerate().find_map(|(y, row)| {
        row.find(needle).map(|byte| {
            let x = row[..byte].chars().count();
            (x as u16, y as u16)
        })
    })
}

// ---- panes ---------------------------------------------------------------------------------

#[test]
fn map_pane() {
    let buf = render(58, 24, panes::render_map);
    assert_screen(&buf, MAP);
    // Drones are coloured by mode: alfa flying, bravo idle, charlie unavailable.
    for (label, mode) in [
        ("●alfa", DroneMode::Flying),
        ("●bravo", DroneMode::Idle),
        ("●charlie", DroneMode::Unavailable),
    ] {
        let (x, y) = find(&buf, label).expect("drone on the map");
        assert_eq!(buf[(x, y)].symbol(), DRONE_MARKER.to_string());
        assert_eq!(buf[(x, y)].fg, panes::mode_color(mode), "{label}");
    }
    let (x, y) = find(&buf, "⌂villa").expect("villa");
    assert_eq!(buf[(x, y)].fg, Color::Magenta);
    let (x, y) = find(&buf, "#business_district").expect("district");
    assert_eq!(buf[(x, y)].fg, Color::LightBlue);
    let (x, y) = find(&buf, "◎dog").expect("target");
    assert_eq!(buf[(x, y)].fg, Color::LightRed);
}

#[test]
fn map_draws_obstacle_footprints_and_every_kind() {
    let mut state = fixed_state();
    let city = Scenario::builtin("city").expect("built in");
    state.world = city.world.clone();
    let area = Rect::new(0, 0, 80, 40);
    let mut buf = Buffer::empty(area);
    panes::render_map(&state, area, &mut buf);
    let screen = text(&buf).join("\n");
    for kind in ["car", "villa", "tree", "skyscraper", "pad"] {
        assert!(screen.contains(kind), "legend lacks {kind}:\n{screen}");
    }
    for symbol in ['▪', '⌂', '♣', '▲', 'H'] {
        assert!(screen.contains(symbol), "no {symbol} on the map:\n{screen}");
    }
    // Each skyscraper's footprint is a circle of radius 8 around its centre.
    let tower = &city.world.obstacles[0];
    let ring = panes::ellipse_footprint(tower, 48);
    assert_eq!(ring.len(), 49);
    for (x, y) in ring {
        let r = ((x - tower.center.x).powi(2) + (y - tower.center.y).powi(2)).sqrt();
        assert!((r - 8.0).abs() < 1e-6, "{r}");
    }
}

#[test]
fn every_kind_of_landmark_has_its_own_marker_and_colour() {
    use tacos_shared::world::LandmarkKind::*;
    let kinds = [Car, Villa, Tree, Skyscraper, Pad, Park, District, Building];
    let looks: Vec<(char, Color)> = kinds.iter().map(|k| panes::landmark_symbol(*k)).collect();
    for (i, a) in looks.iter().enumerate() {
        for b in &looks[i + 1..] {
            assert!(a.0 != b.0 && a.1 != b.1, "{a:?} and {b:?}");
        }
    }
}

#[test]
fn swarm_pane() {
    let buf = render(120, 6, panes::render_swarm);
    assert_screen(&buf, SWARM);
    let (x, y) = find(&buf, "unavailable").expect("charlie's mode");
    assert_eq!(buf[(x, y)].fg, Color::Red);
    let (x, y) = find(&buf, "flying").expect("alfa's mode");
    assert_eq!(buf[(x, y)].fg, Color::LightGreen);
}

#[test]
fn swarm_pane_scrolls_with_twenty_drones() {
    let mut state = fixed_state();
    let t0 = state.now;
    let mut view = SwarmView::default();
    for i in 0..20 {
        view.apply_status(
            status(
                &format!("d{i:02}"),
                DroneMode::Flying,
                [i as f64 * 5.0, 0.0, 10.0],
                [1.0, 0.0, 0.0],
                None,
            ),
            t0,
        );
    }
    state.refresh_swarm(&view, t0);
    assert_eq!(state.drones.len(), 23);
    state.focus = Focus::Swarm;
    state.key(key(KeyCode::PageDown));
    state.key(key(KeyCode::PageDown));
    let area = Rect::new(0, 0, 120, 13);
    let mut buf = Buffer::empty(area);
    panes::render_swarm(&state, area, &mut buf);
    let rows = text(&buf);
    assert!(rows[0].contains("rows 11–20 of 23"), "{}", rows[0]);
    assert!(rows[2].starts_with("│d07 "), "{}", rows[2]);
    assert!(rows[11].starts_with("│d16 "), "{}", rows[11]);
    // Scrolling past the end stops at the last full page.
    for _ in 0..10 {
        state.key(key(KeyCode::PageDown));
    }
    assert_eq!(panes::swarm_first_row(&state, 10), 13);
}

#[test]
fn chat_pane() {
    let buf = render(60, 18, panes::render_chat);
    assert_screen(&buf, CHAT);
}

#[test]
fn chat_scrolls_back_and_follows_again() {
    let mut state = fixed_state();
    state.key(key(KeyCode::PageUp));
    assert_eq!(state.scroll.chat, 5);
    let area = Rect::new(0, 0, 60, 8);
    let mut buf = Buffer::empty(area);
    panes::render_chat(&state, area, &mut buf);
    let rows = text(&buf);
    assert!(
        rows[2].starts_with("│coordinator › The dog hides"),
        "{rows:#?}"
    );
    assert!(rows[7].contains("↓ 5 more lines"), "{rows:#?}");
    state.key(key(KeyCode::PageDown));
    assert_eq!(state.scroll.chat, 0);
    // A submitted line brings the chat back to its end.
    state.key(key(KeyCode::PageUp));
    typed(&mut state, "hold all");
    state.key(key(KeyCode::Enter));
    assert_eq!(state.scroll.chat, 0);
}

#[test]
fn events_pane() {
    let buf = render(60, 12, panes::render_events);
    assert_screen(&buf, EVENTS);
    let (x, y) = find(&buf, "charlie became unavailable").expect("failure");
    assert_eq!(buf[(x, y)].fg, Color::Red);
    let (x, y) = find(&buf, "refused the").expect("rejection");
    assert_eq!(buf[(x, y)].fg, Color::LightRed);
}

#[test]
fn status_bar() {
    let buf = render(120, 1, panes::render_status);
    assert_screen(&buf, STATUS);
    let (x, y) = find(&buf, "supervisor thinking").expect("thinking");
    assert_eq!(buf[(x, y)].fg, Color::Yellow);
}

#[test]
fn input_pane_and_cursor() {
    let mut state = fixed_state();
    typed(&mut state, "alfa, land");
    state.key(key(KeyCode::Left));
    state.key(key(KeyCode::Left));
    let area = Rect::new(0, 0, 60, 3);
    let mut buf = Buffer::empty(area);
    panes::render_input(&state, area, &mut buf);
    assert_screen(
        &buf,
        &[
            "┌ pilot ───────────────────────────────────────────────────┐",
            "│› alfa, land                                              │",
            "└ Enter send · ↑↓ history · Tab focus · PgUp/PgDn scroll · ┘",
        ],
    );
    let cursor = panes::input_cursor(&state, area).expect("a cursor");
    assert_eq!((cursor.x, cursor.y), (11, 1));
    // A long line scrolls so that the cursor stays visible.
    typed(&mut state, &"x".repeat(100));
    let cursor = panes::input_cursor(&state, area).expect("a cursor");
    assert_eq!((cursor.x, cursor.y), (58, 1));
}

#[test]
fn whole_screen_at_120_by_40() {
    let state = fixed_state();
    let mut terminal = Terminal::new(TestBackend::new(120, 40)).expect("test backend");
    terminal.draw(|f| panes::draw(f, &state)).expect("drawn");
    assert_screen(terminal.backend().buffer(), SCREEN);
}

#[test]
fn layout_degrades_without_panicking() {
    let state = fixed_state();
    for (w, h) in [
        (120, 40),
        (100, 24),
        (99, 30),
        (80, 24),
        (59, 20),
        (40, 12),
        (30, 8),
        (20, 5),
        (12, 3),
        (1, 1),
        (0, 0),
    ] {
        let mut terminal = Terminal::new(TestBackend::new(w, h)).expect("test backend");
        terminal.draw(|f| panes::draw(f, &state)).expect("drawn");
        let areas = panes::layout(Rect::new(0, 0, w, h), state.drones.len());
        assert_eq!(areas.map.is_some(), w >= 100 && h >= 24, "{w}×{h}");
        if h >= 5 {
            assert!(areas.status.is_some() && areas.input.height == 3, "{w}×{h}");
        }
    }
    let areas = panes::layout(Rect::new(0, 0, 120, 40), 20);
    assert_eq!(areas.swarm.map(|a| a.height), Some(13));
    assert_eq!(areas.map.map(|a| a.height), Some(23));
}

#[test]
fn drones_sharing_a_map_cell_are_one_marker_with_a_count() {
    let t0 = Instant::now();
    let mut state = TerminalState::new(&lab(), "test", t0);
    let mut view = SwarmView::default();
    // Three drones 0.2 m apart share a cell of a 30-column lab map; a fourth stands apart.
    for (id, x) in [("d1", -3.0), ("d2", -2.8), ("d3", -2.9), ("d4", 3.0)] {
        view.apply_status(
            status(id, DroneMode::Flying, [x, -3.0, 1.0], [0.0; 3], None),
            t0,
        );
    }
    state.refresh_swarm(&view, t0);
    let area = Rect::new(0, 0, 30, 16);
    let mut buf = Buffer::empty(area);
    panes::render_map(&state, area, &mut buf);
    let screen = text(&buf).join("\n");
    assert!(find(&buf, "●d1+2").is_some(), "{screen}");
    assert!(find(&buf, "●d4").is_some(), "{screen}");
    for hidden in ["d2", "d3"] {
        assert!(
            !screen.contains(hidden),
            "{hidden} drawn over its neighbour:\n{screen}"
        );
    }
}
