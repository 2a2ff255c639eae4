//! Headless pilot scripts (`tacos-ground demo --script FILE`): pilot lines with waits and
//! conditions, run without a terminal against a live swarm; the first step that fails ends the
//! run with its line. Used by CI and to replay the paper's demonstrations (`ground/missions/`).
//!
//! One step per line; `#` starts a comment; blank lines are skipped:
//!
//! ```text
//! say <pilot words>                          a pilot line; direct commands are carried out at once
//! wait <seconds>                             let time pass
//! wait until <condition> [within <seconds>]  poll until it holds (default within 600 s)
//! expect <condition>                         must hold now
//! fail <drone> | fail one <state>            the simulator kills that vehicle (for good; on PX4
//!                                            SITL its PX4 instance is killed)
//! ```
//!
//! Conditions: `<who> <state>` with `<who>` = `all` (every drone of the run but those a `fail`
//! step killed), `any`/`some`, a number (at least that many) or a drone's name, optionally
//! followed by `drones`/`is`/`are`; `<state>` = `flying` (in the air, tracking included),
//! `landed`, `tracking [<target>]`, `unavailable`, `near <landmark or target>` (horizontally
//! within twice the map's detection radius). Also `detected <target>` (the simulator's
//! perception reported it), `plan complete` (a plan made after the last `say` completed),
//! `replanned` (the Coordinator made a new plan since the last `fail`) and `no breaches` (the
//! simulator's truth shows no separation or obstacle breach).

pub mod parse;
pub mod run;

pub use parse::{Condition, DroneState, ParseError, Script, Step, StepKind, Victim, Who, parse};
pub use run::{ScriptError, ScriptOptions, ScriptReport, run_script};
