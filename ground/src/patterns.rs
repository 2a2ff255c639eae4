//! Flight patterns flown without a language model, through the same safety gate and link a
//! pilot uses, each phase checked against the simulator's ground truth:
//!
//! - `points`: all take off, each flies to a point north of its pad (spread apart where the pads
//!   are too close for hovering neighbours), all land.
//! - `swap`: all take off, form a circle round the business district, swap to the antipodal
//!   points through the skyscrapers (the distributed planner's test), all land.
//!
//! Both end with the simulator's breach counters: any separation or obstacle breach fails them.

use crate::demo::DemoError;
use crate::direct::run_actions;
use crate::link::GroundLink;
use crate::safety::SafetyGate;
use std::time::{Duration, Instant};
use tacos_shared::action::Action;
use tacos_shared::messages::SimTruth;
use tacos_shared::{DroneId, DroneMode, Vec3};
use tokio::sync::watch;

struct Say {
    start: Instant,
    verbose: bool,
}

impl Say {
    fn line(&self, text: impl AsRef<str>) {
        if self.verbose {
            println!(
                "[{:>6.1}s] {}",
                self.start.elapsed().as_secs_f64(),
                text.as_ref()
            );
        }
    }
}

/// Starts a pattern's narration and waits until every drone is up, linked to its autopilot and
/// on the ground.
async fn wait_until_ready(
    link: &GroundLink,
    ids: &[DroneId],
    verbose: bool,
) -> Result<Say, DemoError> {
    let say = Say {
        start: Instant::now(),
        verbose,
    };
    say.line(format!("waiting for {} drones to come up", ids.len()));
    link.wait_for_drones(ids, Duration::from_secs(60), |s| {
        s.autopilot_link && s.mode == DroneMode::Idle
    })
    .await?;
    say.line("all drones alive, autopilot links up, on the ground");
    Ok(say)
}

/// All take off, each flies to a point north of its pad ([`spread_points`]), all land.
pub async fn fly_points(
    link: &GroundLink,
    gate: &SafetyGate,
    ids: &[DroneId],
    mut truth: watch::Receiver<Option<SimTruth>>,
    verbose: bool,
) -> Result<(), DemoError> {
    let say = wait_until_ready(link, ids, verbose).await?;
    let scenario = gate.scenario();
    let limits = scenario.limits;

    let homes: Vec<Vec3> = ids
        .iter()
        .map(|id| scenario.drone(id).map_or(Vec3::zeros(), |s| s.home))
        .collect();

    phase(
        link,
        gate,
        &say,
        "take off",
        ids.iter()
            .map(|id| (id.clone(), Action::ArmTakeoff))
            .collect(),
        60,
    )
    .await?;
    check_truth(
        &mut truth,
        &say,
        "every vehicle is at take-off altitude",
        |t| {
            unmet(ids.iter().zip(&homes).map(|(id, home)| {
                let up = home.z + 0.8 * limits.takeoff_altitude;
                match vehicle(t, id) {
                    Some(v) if v.armed && v.position.z >= up => None,
                    Some(v) => Some(format!(
                        "{id} at {:.1} m{}",
                        v.position.z,
                        if v.armed { "" } else { ", disarmed" }
                    )),
                    None => Some(format!("{id} not in the truth")),
                }
            }))
        },
    )
    .await?;

    let span = scenario.world.bounds.max.y - scenario.world.bounds.min.y;
    let north: Vec<Vec3> = homes
        .iter()
        .map(|h| Vec3::new(h.x, h.y + 0.1 * span, h.z + limits.takeoff_altitude))
        .collect();
    let goals = spread_points(
        &north,
        POINT_SPACING_IN_SAFETY_DISTANCES * limits.safety_distance,
        |p| {
            scenario
                .world
                .bounds
                .contains_with_margin(p, limits.safety_distance)
                && scenario
                    .world
                    .check_point(p, limits.safety_distance)
                    .is_ok()
        },
    );
    let gotos = ids
        .iter()
        .zip(&goals)
        .map(|(id, g)| (id.clone(), Action::Goto { target: *g }))
        .collect();
    phase(link, gate, &say, "fly to points", gotos, 60).await?;
    let tolerance = arrival_tolerance(gate);
    check_truth(&mut truth, &say, "every vehicle is at its point", |t| {
        at_points(t, ids, &goals, tolerance)
    })
    .await?;
    land_all(link, gate, &say, ids, &mut truth).await?;
    no_breach(&truth, &say)
}

/// The least distance between two drones' points in `points`, in safety distances. Hovering
/// neighbours need more than the safety distance: the planner keeps each pair apart by it plus
/// both drones' tracking margins and the age of the paths they heard, seen through the
/// linearised constraint's angle (about 2.1 safety distances in the lab on PX4 SIH, whose pads
/// are 1 m apart with a 0.6 m safety distance: points that close never settled, issue 14).
pub const POINT_SPACING_IN_SAFETY_DISTANCES: f64 = 2.5;

/// `points` spread about their centre until no two are closer than `spacing`, each kept where
/// it was if its spread place is not `free` (outside the bounds or in an obstacle).
pub fn spread_points(points: &[Vec3], spacing: f64, free: impl Fn(&Vec3) -> bool) -> Vec<Vec3> {
    let closest = points
        .iter()
        .enumerate()
        .flat_map(|(i, a)| points[i + 1..].iter().map(move |b| (a - b).norm()))
        .fold(f64::INFINITY, f64::min);
    if points.len() < 2 || closest >= spacing || closest <= f64::EPSILON {
        return points.to_vec();
    }
    let centre = points.iter().sum::<Vec3>() / points.len() as f64;
    let scale = spacing / closest;
    points
        .iter()
        .map(|p| {
            let spread = centre + (p - centre) * scale;
            if free(&spread) { spread } else { *p }
        })
        .collect()
}

/// Within this distance of its point, a vehicle counts as there in the truth checks.
fn arrival_tolerance(gate: &SafetyGate) -> f64 {
    1.5 * (2.0 * gate.scenario().limits.drone_radius).max(0.2)
}

/// Every vehicle of `ids` within `tolerance` of its point, or those that are not.
fn at_points(t: &SimTruth, ids: &[DroneId], points: &[Vec3], tolerance: f64) -> Result<(), String> {
    unmet(ids.iter().zip(points).map(|(id, p)| match vehicle(t, id) {
        Some(v) if (v.position - p).norm() <= tolerance => None,
        Some(v) => Some(format!("{id} {:.1} m off", (v.position - p).norm())),
        None => Some(format!("{id} not in the truth")),
    }))
}

fn vehicle<'a>(t: &'a SimTruth, id: &DroneId) -> Option<&'a tacos_shared::messages::VehicleTruth> {
    t.vehicles.iter().find(|v| &v.drone == id)
}

/// Ok when nothing is unmet; else what is, as the pilot reads it.
fn unmet(each: impl Iterator<Item = Option<String>>) -> Result<(), String> {
    let unmet: Vec<String> = each.flatten().collect();
    if unmet.is_empty() {
        Ok(())
    } else {
        Err(unmet.join(", "))
    }
}

/// Lands every drone and waits for the truth to show them all down and disarmed.
async fn land_all(
    link: &GroundLink,
    gate: &SafetyGate,
    say: &Say,
    ids: &[DroneId],
    truth: &mut watch::Receiver<Option<SimTruth>>,
) -> Result<(), DemoError> {
    phase(
        link,
        gate,
        say,
        "land",
        ids.iter().map(|id| (id.clone(), Action::Land)).collect(),
        90,
    )
    .await?;
    check_truth(truth, say, "every vehicle has landed and disarmed", |t| {
        unmet(ids.iter().map(|id| match vehicle(t, id) {
            Some(v) if v.landed && !v.armed => None,
            Some(v) => Some(format!(
                "{id} {} at {:.1} m",
                if v.armed { "armed" } else { "disarmed" },
                v.position.z
            )),
            None => Some(format!("{id} not in the truth")),
        }))
    })
    .await
}

/// The simulator's breach counters since it started: any breach fails the pattern.
fn no_breach(truth: &watch::Receiver<Option<SimTruth>>, say: &Say) -> Result<(), DemoError> {
    let Some(t) = truth.borrow().clone() else {
        return Err(DemoError::Step(
            "no ground truth from the simulator to check for breaches".into(),
        ));
    };
    say.line(format!(
        "done: min pair distance {:.2} m, min obstacle clearance {:.2} m, separation breaches {}, obstacle breaches {}",
        t.min_pair_distance, t.min_obstacle_clearance, t.separation_breaches, t.obstacle_breaches
    ));
    if t.separation_breaches > 0 || t.obstacle_breaches > 0 {
        return Err(DemoError::Step(format!(
            "the simulator recorded {} separation and {} obstacle breaches",
            t.separation_breaches, t.obstacle_breaches
        )));
    }
    Ok(())
}

/// Radius of the swap circle round the business district (the skyscrapers stand within 26 m of
/// its centre).
const SWAP_RADIUS: f64 = 60.0;

/// Slot `i` of `n` on the swap circle: evenly spread angles, altitudes spread over 10–20 m so
/// that neighbours on the circle differ in height.
pub fn swap_slot(i: usize, n: usize) -> Vec3 {
    let n = n.max(1);
    let angle = std::f64::consts::TAU * i as f64 / n as f64;
    let altitude = 10.0 + 10.0 * ((i * 7) % n) as f64 / n as f64;
    Vec3::new(
        SWAP_RADIUS * angle.cos(),
        SWAP_RADIUS * angle.sin(),
        altitude,
    )
}

/// All take off, form the circle, swap to the antipodal points through the skyscrapers, land.
pub async fn fly_swap(
    link: &GroundLink,
    gate: &SafetyGate,
    ids: &[DroneId],
    mut truth: watch::Receiver<Option<SimTruth>>,
    verbose: bool,
) -> Result<(), DemoError> {
    let say = wait_until_ready(link, ids, verbose).await?;
    let all = |action: Action| ids.iter().map(|id| (id.clone(), action.clone())).collect();
    phase(link, gate, &say, "take off", all(Action::ArmTakeoff), 60).await?;

    let n = ids.len();
    let slots: Vec<Vec3> = (0..n).map(|i| swap_slot(i, n)).collect();
    let tolerance = arrival_tolerance(gate);
    let at = |goals: &[Vec3]| {
        let goals = goals.to_vec();
        move |t: &SimTruth| at_points(t, ids, &goals, tolerance)
    };
    let to = |goals: &[Vec3]| {
        ids.iter()
            .zip(goals)
            .map(|(id, g)| (id.clone(), Action::Goto { target: *g }))
            .collect()
    };
    phase(link, gate, &say, "form the circle", to(&slots), 180).await?;
    check_truth(&mut truth, &say, "every vehicle is on its slot", at(&slots)).await?;

    let opposite: Vec<Vec3> = slots.iter().map(|p| Vec3::new(-p.x, -p.y, p.z)).collect();
    phase(
        link,
        gate,
        &say,
        "swap through the skyscrapers",
        to(&opposite),
        180,
    )
    .await?;
    check_truth(
        &mut truth,
        &say,
        "every vehicle is at its antipodal point",
        at(&opposite),
    )
    .await?;

    land_all(link, gate, &say, ids, &mut truth).await?;
    no_breach(&truth, &say)
}

/// Runs one phase of the pattern: an action per drone, all at once, all to completion.
async fn phase(
    link: &GroundLink,
    gate: &SafetyGate,
    say: &Say,
    name: &str,
    actions: Vec<(DroneId, Action)>,
    timeout_s: u64,
) -> Result<(), DemoError> {
    say.line(format!("{name}: sending {} actions", actions.len()));
    let task = name.replace(' ', "_");
    run_actions(
        link,
        gate,
        &actions,
        Some(&task),
        Duration::from_secs(timeout_s),
    )
    .await
    .map_err(|e| DemoError::Step(format!("{name}: {e}")))?;
    say.line(format!("{name}: all done"));
    Ok(())
}

/// Waits (bounded) until the simulator's truth satisfies `ok`; a failure says what was unmet in
/// the last truth heard (`ok`'s error).
async fn check_truth(
    truth: &mut watch::Receiver<Option<SimTruth>>,
    say: &Say,
    what: &str,
    ok: impl Fn(&SimTruth) -> Result<(), String>,
) -> Result<(), DemoError> {
    let deadline = tokio::time::Instant::now() + Duration::from_secs(10);
    loop {
        if let Some(t) = truth.borrow().as_ref().filter(|t| ok(t).is_ok()) {
            say.line(format!(
                "simulator truth: {what} (so far: min pair {:.2} m, {} separation / {} obstacle breaches)",
                t.min_pair_distance, t.separation_breaches, t.obstacle_breaches
            ));
            return Ok(());
        }
        match tokio::time::timeout_at(deadline, truth.changed()).await {
            Ok(Ok(())) => {}
            _ => {
                let unmet = match truth.borrow().as_ref().map(&ok) {
                    Some(Err(unmet)) => unmet,
                    Some(Ok(())) => "met only now".to_owned(),
                    None => "no truth heard".to_owned(),
                };
                return Err(DemoError::Step(format!(
                    "simulator truth does not show that {what} within 10 s: {unmet}"
                )));
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn points_closer_than_the_spacing_are_spread_about_their_centre() {
        let lab = [
            Vec3::new(-1.0, -2.7, 1.0),
            Vec3::new(0.0, -2.7, 1.0),
            Vec3::new(1.0, -2.7, 1.0),
        ];
        let spread = spread_points(&lab, 1.5, |_| true);
        assert_eq!(spread[1], lab[1], "the centre stays");
        assert!((spread[0] - Vec3::new(-1.5, -2.7, 1.0)).norm() < 1e-9);
        assert!((spread[2] - Vec3::new(1.5, -2.7, 1.0)).norm() < 1e-9);

        let far = [Vec3::new(0.0, 0.0, 1.0), Vec3::new(5.0, 0.0, 1.0)];
        assert_eq!(spread_points(&far, 1.5, |_| true), far.to_vec());
    }

    #[test]
    fn a_spread_point_that_is_not_free_stays_where_it_was() {
        let points = [Vec3::new(0.0, 0.0, 1.0), Vec3::new(1.0, 0.0, 1.0)];
        let spread = spread_points(&points, 2.0, |p| p.x < 1.2);
        assert!((spread[0] - Vec3::new(-0.5, 0.0, 1.0)).norm() < 1e-9);
        assert_eq!(spread[1], points[1]);
    }
}
