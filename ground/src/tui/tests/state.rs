//! The terminal state's own rules, without rendering: keys and editing, history, updates in
//! order, the thinking timer, trails, untrusted text, wrapping, the approval switch.

use super::*;
// ---- state ---------------------------------------------------------------------------------

#[test]
fn key_editing() {
    let mut state = TerminalState::new(&lab(), "test", Instant::now());
    typed(&mut state, "alfa tkeoff");
    for _ in 0..5 {
        state.key(key(KeyCode::Left));
    }
    state.key(key(KeyCode::Char('a')));
    assert_eq!(state.input.text(), "alfa takeoff");
    assert_eq!(state.input.cursor(), 7);
    state.key(key(KeyCode::Home));
    state.key(key(KeyCode::Delete));
    state.key(key(KeyCode::Char('A')));
    assert_eq!(state.input.text(), "Alfa takeoff");
    state.key(key(KeyCode::End));
    state.key(key(KeyCode::Backspace));
    assert_eq!(state.input.text(), "Alfa takeof");
    state.key(ctrl('w'));
    assert_eq!(state.input.text(), "Alfa ");
    state.key(ctrl('a'));
    state.key(key(KeyCode::Right));
    state.key(ctrl('k'));
    assert_eq!(state.input.text(), "A");
    state.key(ctrl('e'));
    typed(&mut state, "b c");
    state.key(key(KeyCode::Left));
    state.key(ctrl('u'));
    assert_eq!(
        (state.input.text().as_str(), state.input.cursor()),
        ("c", 0)
    );
    // Multi-byte characters are edited as characters.
    state.key(key(KeyCode::End));
    typed(&mut state, "é→");
    state.key(key(KeyCode::Backspace));
    assert_eq!(state.input.text(), "cé");
    // Blank lines are not submitted; quitting.
    state.key(ctrl('u'));
    state.key(key(KeyCode::Backspace));
    state.key(key(KeyCode::End));
    state.key(ctrl('u'));
    typed(&mut state, "   ");
    assert_eq!(state.key(key(KeyCode::Enter)), None);
    typed(&mut state, ":q");
    assert_eq!(state.key(key(KeyCode::Enter)), Some(Command::Quit));
    assert_eq!(state.key(key(KeyCode::Esc)), Some(Command::Quit));
    assert_eq!(state.key(ctrl('c')), Some(Command::Quit));
    assert!(state.chat.is_empty());
}

#[test]
fn history_up_and_down() {
    let mut state = TerminalState::new(&lab(), "test", Instant::now());
    for line in ["alfa, take off", "land all", "land all", "hold all"] {
        typed(&mut state, line);
        assert_eq!(
            state.key(key(KeyCode::Enter)),
            Some(Command::Submit(line.into()))
        );
    }
    // Repeats are kept once.
    assert_eq!(
        state.input.history(),
        ["alfa, take off", "land all", "hold all"]
    );
    typed(&mut state, "draft");
    state.key(key(KeyCode::Up));
    assert_eq!(state.input.text(), "hold all");
    state.key(key(KeyCode::Up));
    state.key(key(KeyCode::Up));
    state.key(key(KeyCode::Up));
    assert_eq!(state.input.text(), "alfa, take off");
    assert_eq!(state.input.cursor(), "alfa, take off".chars().count());
    state.key(key(KeyCode::Down));
    assert_eq!(state.input.text(), "land all");
    state.key(key(KeyCode::Down));
    state.key(key(KeyCode::Down));
    assert_eq!(state.input.text(), "draft");
    state.key(key(KeyCode::Down));
    assert_eq!(state.input.text(), "draft");
    // An edited history line is submitted as a new line.
    state.key(key(KeyCode::Up));
    typed(&mut state, " now");
    assert_eq!(
        state.key(key(KeyCode::Enter)),
        Some(Command::Submit("hold all now".into()))
    );
    assert_eq!(state.input.text(), "");
    assert_eq!(
        state.chat.back(),
        Some(&ChatEntry::Pilot("hold all now".into()))
    );
}

#[test]
fn updates_land_in_order() {
    let state = fixed_state();
    let chat: Vec<&str> = state
        .chat
        .iter()
        .map(|e| match e {
            ChatEntry::Pilot(_) => "pilot",
            ChatEntry::Coordinator { .. } => "coordinator",
            ChatEntry::Supervisor { cycle: 1, .. } => "cycle 1",
            ChatEntry::Supervisor { .. } => "cycle n",
            ChatEntry::PlanComplete { .. } => "complete",
            ChatEntry::Error(_) => "error",
        })
        .collect();
    assert_eq!(chat, ["pilot", "coordinator", "cycle 1", "cycle n"]);
    let kinds: Vec<EventKind> = state.events.iter().map(|e| e.kind).collect();
    assert_eq!(
        kinds,
        [
            EventKind::Sent,
            EventKind::Done,
            EventKind::Failure,
            EventKind::Rejected,
            EventKind::Sent
        ]
    );
    let times: Vec<f64> = state.events.iter().map(|e| e.at.as_secs_f64()).collect();
    assert!(times.windows(2).all(|w| w[0] <= w[1]), "{times:?}");
    assert_eq!(state.status.calls, 4);
    assert_eq!(
        state.status.last_call.as_ref().map(|c| c.latency),
        Some(Duration::from_millis(400))
    );

    // A second plan while one runs is a replan; after completion it is not.
    let mut state = state;
    let now = state.now;
    let plan = MissionUpdate::Plan {
        reasoning: "charlie is lost; bravo takes over".into(),
        calls: vec!["t3 bravo arm_takeoff()".into()],
    };
    state.apply_update(&plan, now);
    assert_eq!(state.events.back().map(|e| e.kind), Some(EventKind::Replan));
    state.apply_update(&MissionUpdate::PlanComplete { cycles: 4 }, now);
    let before = state.events.len();
    state.apply_update(&plan, now);
    assert_eq!(state.events.len(), before);
    // Detections and direct commands are told apart.
    state.apply_update(
        &MissionUpdate::Event {
            topic: EventTopic::Detection,
            text: "dog seen at small_park by alfa".into(),
        },
        now,
    );
    state.apply_update(
        &MissionUpdate::Event {
            topic: EventTopic::Direct,
            text: "direct command \"land all\": alfa: sent #12".into(),
        },
        now,
    );
    state.apply_update(
        &MissionUpdate::Error("coordinator: the model server failed".into()),
        now,
    );
    let last: Vec<EventKind> = state.events.iter().rev().take(3).map(|e| e.kind).collect();
    assert_eq!(
        last,
        [EventKind::Error, EventKind::Direct, EventKind::Detection]
    );
    assert_eq!(
        state.chat.back(),
        Some(&ChatEntry::Error(
            "coordinator: the model server failed".into()
        ))
    );
    assert!(state.status.thinking.is_none());
}

#[test]
fn thinking_timer() {
    let t0 = Instant::now();
    let mut state = TerminalState::new(&lab(), "test", t0);
    assert_eq!(state.thinking_for(), None);
    state.apply_update(
        &MissionUpdate::Thinking {
            layer: "coordinator",
        },
        at(t0, 1.0),
    );
    state.tick(at(t0, 4.2));
    let (layer, secs) = state.thinking_for().expect("thinking");
    assert_eq!(layer, "coordinator");
    assert!((secs - 3.2).abs() < 1e-9, "{secs}");
    // Time never runs backwards.
    state.tick(at(t0, 2.0));
    assert!((state.thinking_for().expect("thinking").1 - 3.2).abs() < 1e-9);
    // The answer stops the timer; a rejected reply that goes back starts it again.
    let call = MissionUpdate::Call {
        layer: "coordinator",
        latency: Duration::from_millis(3200),
        prompt_tokens: 10,
        completion_tokens: 5,
    };
    state.apply_update(&call, at(t0, 4.2));
    assert_eq!(state.thinking_for(), None);
    state.apply_update(
        &MissionUpdate::Rejected {
            layer: "coordinator",
            refusal: "t1 zulu land()".into(),
            by: RefusedBy::Checks,
        },
        at(t0, 4.3),
    );
    state.tick(at(t0, 5.3));
    let (layer, secs) = state.thinking_for().expect("thinking again");
    assert_eq!(layer, "coordinator");
    assert!((secs - 1.0).abs() < 1e-9);
    state.apply_update(
        &MissionUpdate::Plan {
            reasoning: String::new(),
            calls: Vec::new(),
        },
        at(t0, 5.4),
    );
    assert_eq!(state.thinking_for(), None);
}

#[test]
fn trails_are_decimated_and_expire() {
    let t0 = Instant::now();
    let mut state = TerminalState::new(&lab(), "test", t0);
    let mut view = SwarmView::default();
    // 10 Hz refreshes for 100 s while alfa moves east at 0.1 m/s.
    for i in 0..1000 {
        let now = at(t0, f64::from(i) * 0.1);
        view.apply_status(
            status(
                "alfa",
                DroneMode::Flying,
                [f64::from(i) * 0.01, 0.0, 1.0],
                [0.1, 0.0, 0.0],
                None,
            ),
            now,
        );
        state.refresh_swarm(&view, now);
    }
    let trail = state.trails.get("alfa").expect("a trail");
    let span = TRAIL_SPAN.as_secs_f64() / TRAIL_STEP.as_secs_f64();
    assert!(
        (trail.len() as f64 - span).abs() <= 1.0,
        "{} points",
        trail.len()
    );
    let oldest = trail.front().map(|(t, _)| *t).expect("points");
    assert!(state.now.duration_since(oldest) <= TRAIL_SPAN);
    for pair in trail.iter().collect::<Vec<_>>().windows(2) {
        assert!(pair[1].0.duration_since(pair[0].0) >= TRAIL_STEP);
    }
    // bravo, charlie never reported: no trail, shown as unavailable without data.
    assert_eq!(state.trails.len(), 1);
    assert!(state.drones[1].position.is_none());
    assert_eq!(state.drones[1].mode, DroneMode::Unavailable);
    // A silent drone's trail empties after the span.
    state.refresh_swarm(
        &SwarmView::default(),
        at(t0, 100.0 + TRAIL_SPAN.as_secs_f64() + 1.0),
    );
    assert!(state.trails.is_empty());
}

#[test]
fn outside_data_is_not_trusted() {
    let t0 = Instant::now();
    let mut state = TerminalState::new(&lab(), "test", t0);
    let mut view = SwarmView::default();
    view.apply_status(
        status(
            "alfa",
            DroneMode::Flying,
            [f64::NAN, 0.0, 1.0],
            [f64::INFINITY, 0.0, 0.0],
            None,
        ),
        t0,
    );
    state.refresh_swarm(&view, t0);
    assert!(state.drones[0].position.is_none() && state.drones[0].velocity.is_none());
    assert!(state.trails.is_empty());
    state.set_targets(&[TargetObservation {
        name: "ghost".into(),
        position: Vec3::new(f64::NAN, 0.0, 0.0),
        velocity: Vec3::zeros(),
    }]);
    assert!(state.targets.is_empty());
    // Rendering such a state is fine.
    let mut terminal = Terminal::new(TestBackend::new(120, 40)).expect("test backend");
    terminal.draw(|f| panes::draw(f, &state)).expect("drawn");
}

#[test]
fn wrap_cuts_long_words_and_keeps_paragraphs() {
    assert_eq!(panes::wrap("a bb ccc dddd", 6), ["a bb", "ccc", "dddd"]);
    assert_eq!(panes::wrap("abcdefghij", 4), ["abcd", "efgh", "ij"]);
    assert_eq!(panes::wrap("one\ntwo", 10), ["one", "two"]);
    assert_eq!(panes::wrap("", 10), [""]);
}

#[test]
fn f2_switches_plan_approval_and_the_status_bar_shows_it() {
    let mut state = TerminalState::new(&lab(), "test", Instant::now());
    let bar = |state: &TerminalState| -> String {
        crate::tui::panes::status_line(state)
            .spans
            .iter()
            .map(|s| s.content.as_ref())
            .collect()
    };
    assert!(!bar(&state).contains("confirm"));
    assert_eq!(
        state.key(key(KeyCode::F(2))),
        Some(Command::Submit("confirm on".into()))
    );
    assert!(bar(&state).contains("confirm (F2)"), "{}", bar(&state));
    assert_eq!(
        state.key(key(KeyCode::F(2))),
        Some(Command::Submit("confirm off".into()))
    );
    assert!(!bar(&state).contains("confirm"));
}
