use super::*;
use crate::mission::aids::ModelAids;
use tacos_prompts::ActionName;

fn line(t: f64, record: Record) -> Line {
    Line { t, record }
}

fn start(mode: &str, format: u32) -> Record {
    Record::MissionStart {
        mode: mode.into(),
        backend: "stand-in".into(),
        scenario: "city".into(),
        drones: vec!["alfa".into(), "bravo".into()],
        aids: ModelAids::small(),
        format,
    }
}

fn task(call: Call) -> PlanTask {
    PlanTask {
        call,
        status: TaskStatus::NotStarted,
        sent: None,
        failures: 0,
    }
}

fn sent(drone: &str, task: &str, seq: u64) -> Record {
    Record::ActionSent {
        drone: drone.into(),
        task: Some(task.into()),
        seq,
        action: String::new(),
        checked: None,
    }
}

fn outcome(drone: &str, task: &str, seq: u64, failure: Option<&str>) -> Record {
    Record::ActionOutcome {
        drone: drone.into(),
        task: Some(task.into()),
        seq,
        outcome: match failure {
            Some(why) => format!("failed: {why}"),
            None => "done".into(),
        },
        failure: failure.map(str::to_owned),
    }
}

/// Alfa takes off (T1) and flies to the villa (T2), bravo flies to the park (T3): the log of
/// a ground killed while T2 ran and T3, failed once on bravo, had been sent to bravo again.
fn killed_mid_plan() -> Vec<Line> {
    let plan = vec![
        task(Call::named("T1", "alfa", ActionName::ArmTakeoff, "none")),
        task(Call::named("T2", "alfa", ActionName::Goto, "villa")),
        task(Call::named(
            "T3",
            "bravo",
            ActionName::Goto,
            "large_park_north",
        )),
    ];
    let pilot = "alfa to the villa, bravo to the park";
    vec![
        line(0.0, start("tacos", LOG_FORMAT)),
        line(1.0, Record::Pilot { text: pilot.into() }),
        line(
            1.0,
            Record::History {
                entry: HistoryEntry::Pilot(pilot.into()),
            },
        ),
        line(
            2.0,
            Record::WorldEvent {
                text: "detection: dog near the villa".into(),
            },
        ),
        line(
            4.0,
            Record::PlanAdopted {
                reasoning: "split".into(),
                tasks: plan,
            },
        ),
        line(5.0, sent("alfa", "T1", 100)),
        line(5.0, sent("bravo", "T3", 101)),
        line(
            5.0,
            Record::SupervisorCycle {
                plan_cycle: 1,
                actions: vec![],
                plan_complete: false,
            },
        ),
        line(9.0, outcome("alfa", "T1", 100, None)),
        line(
            9.5,
            outcome("bravo", "T3", 101, Some("bravo is on the ground")),
        ),
        line(10.0, sent("alfa", "T2", 102)),
        line(10.0, sent("bravo", "T3", 103)),
        line(
            10.0,
            Record::SupervisorCycle {
                plan_cycle: 2,
                actions: vec![],
                plan_complete: false,
            },
        ),
        // Positions and model traffic change nothing.
        line(
            11.0,
            Record::Position {
                drone: "alfa".into(),
                x: 0.0,
                y: 0.0,
                z: 10.0,
                speed: 3.0,
            },
        ),
    ]
}

#[test]
fn a_plan_killed_mid_flight_comes_back_with_each_task_where_it_stood() {
    let resumable = rebuild(&killed_mid_plan()).expect("resumable");
    assert_eq!(resumable.mode, "tacos");
    assert_eq!(resumable.scenario, "city");
    assert_eq!(resumable.ended, None);
    let memory = &resumable.memory;
    assert_eq!(
        memory.history,
        vec![HistoryEntry::Pilot(
            "alfa to the villa, bravo to the park".into()
        )]
    );
    assert_eq!(memory.world_events, vec!["detection: dog near the villa"]);
    let plan = memory.plan.as_ref().expect("the plan in force");
    assert_eq!(plan.cycles, 2);
    let states: Vec<(&str, &TaskStatus, Option<u64>, u32)> = plan
        .tasks
        .iter()
        .map(|t| {
            (
                t.call.task.as_str(),
                &t.status,
                t.sent.as_ref().map(|(_, s)| *s),
                t.failures,
            )
        })
        .collect();
    assert_eq!(
        states,
        vec![
            ("T1", &TaskStatus::Done, Some(100), 0),
            ("T2", &TaskStatus::Running, Some(102), 0),
            ("T3", &TaskStatus::Running, Some(103), 1),
        ]
    );
    // The Supervisor's memory of the plan, as its prompt shows it.
    let progress: Vec<_> = plan.tasks.iter().map(PlanTask::progress).collect();
    assert_eq!(
        tacos_prompts::render::plan_memory(&progress),
        "- T1: done\n- T2: running\n- T3: running, after 1 failure\n- every task issued\n"
    );
}

#[test]
fn a_failed_task_sent_to_another_drone_is_that_drones_and_an_outcome_of_another_seq_is_not_its() {
    let mut lines = killed_mid_plan();
    lines.push(line(12.0, outcome("bravo", "T3", 101, Some("late"))));
    lines.push(line(12.0, outcome("alfa", "T3", 103, None)));
    lines.push(line(13.0, sent("alfa", "T3", 104)));
    let plan = rebuild(&lines)
        .expect("resumable")
        .memory
        .plan
        .expect("plan");
    let t3 = &plan.tasks[2];
    assert_eq!(t3.call.drone, "alfa");
    assert_eq!(t3.status, TaskStatus::Running);
    assert_eq!(
        t3.sent.as_ref().map(|(d, s)| (d.as_str(), *s)),
        Some(("alfa", 104))
    );
    assert_eq!(t3.failures, 1, "outcomes of other sends did not count");
}

#[test]
fn an_ended_plan_is_not_resumed_and_a_second_resume_starts_from_the_first() {
    let mut lines = killed_mid_plan();
    lines.push(line(
        20.0,
        Record::PlanEnded {
            how: "interrupted by a direct command".into(),
        },
    ));
    let ended = rebuild(&lines).expect("resumable");
    assert_eq!(ended.memory.plan, None);
    assert_eq!(ended.memory.history.len(), 1, "the history stays");

    // The first resume writes what it went on from; the second reads that, then what followed.
    let first = rebuild(&killed_mid_plan()).expect("resumable").memory;
    let again = vec![
        line(0.0, start("tacos", LOG_FORMAT)),
        line(
            0.1,
            Record::Resumed {
                from: "mission.jsonl".into(),
                memory: first,
            },
        ),
        line(3.0, outcome("alfa", "T2", 102, None)),
        line(3.0, outcome("bravo", "T3", 103, None)),
        line(3.5, Record::PlanComplete { cycles: 3 }),
        line(
            4.0,
            Record::MissionEnd {
                outcome: "pilot closed the session".into(),
            },
        ),
    ];
    let second = rebuild(&again).expect("resumable");
    assert_eq!(
        second.memory.plan, None,
        "the plan completed after the resume"
    );
    assert_eq!(second.memory.world_events.len(), 1);
    assert_eq!(second.ended.as_deref(), Some("pilot closed the session"));
}

#[test]
fn logs_that_cannot_be_resumed_say_why() {
    assert_eq!(rebuild(&[]), Err(ResumeError::NoMission));
    assert_eq!(
        rebuild(&[line(0.0, start("tacos", 0))]),
        Err(ResumeError::TooOld { found: 0 })
    );
    assert_eq!(
        rebuild(&[line(0.0, start("mnl", LOG_FORMAT))]),
        Err(ResumeError::Monolithic { mode: "mnl".into() })
    );
    // A log reused after a crash: the last mission is the one resumed.
    let mut lines = vec![line(0.0, start("mnl", LOG_FORMAT))];
    lines.extend(killed_mid_plan());
    assert!(rebuild(&lines).is_ok());
}

#[test]
fn the_memory_reads_back_as_it_was_written() {
    let memory = rebuild(&killed_mid_plan()).expect("resumable").memory;
    let record = Record::Resumed {
        from: "m.jsonl".into(),
        memory: memory.clone(),
    };
    let text = serde_json::to_string(&Line { t: 1.0, record }).expect("written");
    let back: Line = serde_json::from_str(&text).expect("read");
    assert_eq!(
        back.record,
        Record::Resumed {
            from: "m.jsonl".into(),
            memory
        }
    );
}
