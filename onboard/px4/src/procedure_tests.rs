//! Tests of [`super::Procedures`]: the PX4 sequences measured on PX4 SITL.

use super::*;

/// Procedures whose autopilot setup is done (its own tests are in `setup`).
fn ready_procedures() -> Procedures {
    let mut p = Procedures::new();
    p.on_setup(SetupState::Done);
    p
}

fn at(t0: Instant, ms: u64) -> Instant {
    t0 + Duration::from_millis(ms)
}

fn facts(mode: Px4Mode, ready: bool) -> AutopilotFacts {
    AutopilotFacts {
        link_ok: true,
        ready,
        armed: false,
        mode,
        amsl_m: Some(489.4),
    }
}

fn sent(events: &[ProcedureEvent]) -> Vec<(u16, [f32; 7])> {
    events
        .iter()
        .filter_map(|e| match e {
            ProcedureEvent::Send(m) => Some((m.command, m.params)),
            _ => None,
        })
        .collect()
}

fn done(events: &[ProcedureEvent]) -> Vec<CommandResultSample> {
    events
        .iter()
        .filter_map(|e| match e {
            ProcedureEvent::Done(r) => Some(*r),
            _ => None,
        })
        .collect()
}

fn commands(events: &[ProcedureEvent]) -> Vec<u16> {
    sent(events).iter().map(|(c, _)| *c).collect()
}

#[test]
fn arm_waits_for_the_preflight_checks_then_arms() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    assert!(
        p.submit(CommandSample::new(1, CommandKind::Arm, 0.0))
            .is_none()
    );
    let booting = facts(Px4Mode::Hold, false);
    assert!(
        p.poll(t0, &booting).is_empty(),
        "nothing is sent before PX4 is ready"
    );
    assert!(p.poll(at(t0, 5000), &booting).is_empty());
    let ready = facts(Px4Mode::Hold, true);
    let ev = p.poll(at(t0, 6000), &ready);
    assert_eq!(commands(&ev), vec![mav_cmd::COMPONENT_ARM_DISARM]);
    let ev = p.on_ack(400, mav_result::ACCEPTED, at(t0, 6010), &ready);
    let results = done(&ev);
    assert_eq!(results.len(), 1);
    assert_eq!(
        (results[0].seq, results[0].outcome(), results[0].reason()),
        (1, Some(CommandOutcome::Accepted), None)
    );
    assert!(p.is_idle());
}

#[test]
fn an_arm_never_ready_fails_in_px4s_words() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
    let booting = facts(Px4Mode::Hold, false);
    p.poll(t0, &booting);
    p.on_status_text("Preflight Fail: heading estimate invalid", at(t0, 29_000));
    assert!(p.poll(at(t0, 29_999), &booting).is_empty());
    let results = done(&p.poll(at(t0, 30_000), &booting));
    assert_eq!(results.len(), 1);
    assert_eq!(results[0].outcome(), Some(CommandOutcome::Rejected));
    let reason = results[0].reason().unwrap_or_default();
    assert!(reason.contains("not ready to arm after 30 s"), "{reason}");
    assert!(
        reason.contains("Preflight Fail: heading estimate invalid"),
        "{reason}"
    );
}

#[test]
fn after_an_offboard_flight_the_arm_switches_to_hold_first() {
    // PX4 lands back in OFFBOARD with system_status 0 and refuses to arm there.
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(2, CommandKind::Arm, 0.0));
    let landed = facts(Px4Mode::Offboard, false);
    let ev = p.poll(t0, &landed);
    assert_eq!(
        sent(&ev),
        vec![(176, [1.0, 4.0, 3.0, 0.0, 0.0, 0.0, 0.0])],
        "DO_SET_MODE AUTO.LOITER"
    );
    // The first ack is always ACCEPTED; the heartbeat then shows Hold and PX4 gets ready.
    assert!(
        p.on_ack(176, mav_result::ACCEPTED, at(t0, 5), &landed)
            .is_empty()
    );
    assert!(p.poll(at(t0, 500), &landed).is_empty());
    let in_hold = facts(Px4Mode::Hold, false);
    assert!(
        p.poll(at(t0, 900), &in_hold).is_empty(),
        "still waiting for readiness"
    );
    let ev = p.poll(at(t0, 1200), &facts(Px4Mode::Hold, true));
    assert_eq!(commands(&ev), vec![400]);
}

#[test]
fn take_off_sends_an_amsl_altitude() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(3, CommandKind::Takeoff, 5.0));
    let mut armed = facts(Px4Mode::Hold, true);
    armed.armed = true;
    armed.amsl_m = Some(489.37);
    let ev = p.poll(t0, &armed);
    let s = sent(&ev);
    assert_eq!(s.len(), 1);
    assert_eq!(s[0].0, mav_cmd::NAV_TAKEOFF);
    assert!(
        (f64::from(s[0].1[6]) - 494.37).abs() < 1e-3,
        "param7 {}",
        s[0].1[6]
    );
}

#[test]
fn take_off_asks_for_the_altitude_and_fails_clearly_without_it() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(3, CommandKind::Takeoff, 5.0));
    let mut unknown = facts(Px4Mode::Hold, true);
    unknown.amsl_m = None;
    let ev = p.poll(t0, &unknown);
    assert_eq!(sent(&ev), vec![(512, [33.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])]);
    let ev = p.on_ack(512, mav_result::ACCEPTED, at(t0, 5), &unknown);
    assert_eq!(
        ev,
        vec![ProcedureEvent::Internal {
            command: 512,
            outcome: AckOutcome::Accepted
        }]
    );
    assert!(p.poll(at(t0, 4999), &unknown).is_empty());
    let results = done(&p.poll(at(t0, 5000), &unknown));
    assert_eq!(results.len(), 1);
    assert_eq!(results[0].outcome(), Some(CommandOutcome::Rejected));
    assert!(results[0].reason().unwrap_or_default().contains("AMSL"));
    // The altitude arriving in time is used.
    p.submit(CommandSample::new(4, CommandKind::Takeoff, 2.0));
    p.poll(at(t0, 6000), &unknown);
    p.on_ack(512, mav_result::ACCEPTED, at(t0, 6005), &unknown);
    let ev = p.poll(at(t0, 6100), &facts(Px4Mode::Hold, true));
    assert!(
        sent(&ev)
            .iter()
            .any(|(c, params)| *c == 22 && params[6] > 491.0)
    );
}

#[test]
fn a_mode_switch_refused_in_the_second_ack_is_refused() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(5, CommandKind::Offboard, 0.0));
    let hold = facts(Px4Mode::Hold, true);
    assert_eq!(commands(&p.poll(t0, &hold)), vec![176]);
    assert!(
        p.on_ack(176, mav_result::ACCEPTED, at(t0, 2), &hold)
            .is_empty()
    );
    p.on_status_text(
        "Switching to Offboard is currently not available",
        at(t0, 3),
    );
    let ev = p.on_ack(176, mav_result::TEMPORARILY_REJECTED, at(t0, 4), &hold);
    let results = done(&ev);
    assert_eq!(results.len(), 1);
    assert_eq!(
        (results[0].outcome(), results[0].mav_result),
        (Some(CommandOutcome::Rejected), 1)
    );
    assert!(
        results[0]
            .reason()
            .unwrap_or_default()
            .contains("Switching to Offboard is currently not available")
    );
}

#[test]
fn a_mode_switch_is_done_when_the_heartbeat_shows_it_or_the_second_ack_accepts() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(6, CommandKind::Offboard, 0.0));
    let hold = facts(Px4Mode::Hold, true);
    p.poll(t0, &hold);
    p.on_ack(176, mav_result::ACCEPTED, at(t0, 2), &hold);
    assert!(
        p.poll(at(t0, 800), &hold).is_empty(),
        "not done on the first ack"
    );
    let ev = p.poll(at(t0, 900), &facts(Px4Mode::Offboard, true));
    assert_eq!(
        done(&ev).first().and_then(|r| r.outcome()),
        Some(CommandOutcome::Accepted)
    );

    p.submit(CommandSample::new(7, CommandKind::Hold, 0.0));
    let off = facts(Px4Mode::Offboard, true);
    p.poll(at(t0, 1000), &off);
    p.on_ack(176, mav_result::ACCEPTED, at(t0, 1002), &off);
    let ev = p.on_ack(176, mav_result::ACCEPTED, at(t0, 1003), &off);
    assert_eq!(done(&ev).first().map(|r| r.seq), Some(7));

    // Neither: refused after the bound, saying what PX4 still shows.
    p.submit(CommandSample::new(8, CommandKind::Offboard, 0.0));
    p.poll(at(t0, 2000), &hold);
    p.on_ack(176, mav_result::ACCEPTED, at(t0, 2001), &hold);
    let ev = p.poll(at(t0, 2001) + MODE_CONFIRM_TIMEOUT, &hold);
    let results = done(&ev);
    assert_eq!(
        results.first().and_then(|r| r.outcome()),
        Some(CommandOutcome::Rejected)
    );
    assert!(
        results[0]
            .reason()
            .unwrap_or_default()
            .contains("still reports Hold")
    );
}

#[test]
fn a_refused_arm_carries_the_statustext_and_bad_commands_are_unsupported() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(9, CommandKind::Arm, 0.0));
    let ready = facts(Px4Mode::Hold, true);
    p.poll(t0, &ready);
    p.on_status_text(
        "Arming denied: Resolve system health failures first",
        at(t0, 3),
    );
    let results = done(&p.on_ack(400, mav_result::TEMPORARILY_REJECTED, at(t0, 4), &ready));
    assert_eq!(results[0].mav_result, 1);
    assert!(
        results[0]
            .reason()
            .unwrap_or_default()
            .contains("Arming denied")
    );

    let unknown = CommandSample {
        seq: 10,
        kind: 99,
        _reserved: 0,
        param: 0.0,
    };
    assert_eq!(
        p.submit(unknown).and_then(|r| r.outcome()),
        Some(CommandOutcome::Unsupported)
    );
    assert_eq!(
        p.submit(CommandSample::new(11, CommandKind::Takeoff, f64::INFINITY))
            .map(|r| (r.seq, r.outcome())),
        Some((11, Some(CommandOutcome::Unsupported)))
    );
}

#[test]
fn commands_wait_for_each_other_and_a_lost_link_ends_them() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
    p.submit(CommandSample::new(2, CommandKind::Land, 0.0));
    let booting = facts(Px4Mode::Hold, false);
    assert!(
        p.poll(t0, &booting).is_empty(),
        "the land waits behind the arm"
    );
    let mut lost = booting;
    lost.link_ok = false;
    let ev = p.poll(at(t0, 100), &lost);
    let results = done(&ev);
    assert_eq!(
        results
            .iter()
            .map(|r| (r.seq, r.outcome()))
            .collect::<Vec<_>>(),
        vec![
            (1, Some(CommandOutcome::LinkLost)),
            (2, Some(CommandOutcome::LinkLost))
        ]
    );
}

#[test]
fn arming_waits_for_the_setup_and_a_failed_setup_refuses_with_its_reason() {
    let t0 = Instant::now();
    let mut p = Procedures::new();
    p.submit(CommandSample::new(1, CommandKind::Arm, 0.0));
    let ready = facts(Px4Mode::Hold, true);
    assert!(
        p.poll(t0, &ready).is_empty(),
        "no arming before the failsafe parameters are set"
    );
    p.on_setup(SetupState::Done);
    assert_eq!(commands(&p.poll(at(t0, 100), &ready)), vec![400]);

    let mut p = Procedures::new();
    p.submit(CommandSample::new(2, CommandKind::Arm, 0.0));
    p.poll(t0, &ready);
    p.on_setup(SetupState::Failed(
        "parameter COM_OBL_RC_ACT was not set to 5".into(),
    ));
    let results = done(&p.poll(at(t0, 100), &ready));
    assert_eq!(results.len(), 1);
    let reason = results[0].reason().unwrap_or_default();
    assert!(reason.contains("COM_OBL_RC_ACT"), "{reason}");
}

#[test]
fn in_offboard_with_setpoints_streaming_the_arm_is_sent_there() {
    // The onboard's take-off: setpoints stream, PX4 is switched to OFFBOARD and reports ready.
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(2, CommandKind::Arm, 0.0));
    let ev = p.poll(t0, &facts(Px4Mode::Offboard, true));
    assert_eq!(commands(&ev), vec![mav_cmd::COMPONENT_ARM_DISARM]);
}

#[test]
fn an_offboard_switch_on_the_ground_waits_for_the_preflight_checks() {
    let t0 = Instant::now();
    let mut p = ready_procedures();
    p.submit(CommandSample::new(4, CommandKind::Offboard, 0.0));
    let booting = facts(Px4Mode::Hold, false);
    assert!(
        p.poll(t0, &booting).is_empty(),
        "refused by PX4 before ready"
    );
    let ev = p.poll(at(t0, 3000), &facts(Px4Mode::Hold, true));
    assert_eq!(
        sent(&ev),
        vec![(176, [1.0, 6.0, 0.0, 0.0, 0.0, 0.0, 0.0])],
        "DO_SET_MODE OFFBOARD"
    );
    // Never ready: it fails with the time it waited.
    let mut p = ready_procedures();
    p.submit(CommandSample::new(5, CommandKind::Offboard, 0.0));
    p.poll(t0, &booting);
    let results = done(&p.poll(at(t0, 30_000), &booting));
    assert_eq!(results.len(), 1);
    assert_eq!(results[0].outcome(), Some(CommandOutcome::Rejected));
    let reason = results[0].reason().unwrap_or_default();
    assert!(
        reason.contains("not ready for offboard control"),
        "{reason}"
    );
}
