//! Turns a model's call into a concrete action: a landmark or a moving target named in a goto
//! becomes a point, at an altitude low enough for the perception stand-in to see what is there,
//! and clear of the points other drones hold or are headed for (two drones sent to one car must
//! not both be given the same point: the planner keeps them apart and the second would never
//! arrive). An explicit point that another drone holds or is headed for is refused with the
//! reason, for the same cause: the goto could only time out.

use crate::swarm::SwarmView;
use std::time::Instant;
use tacos_prompts::{ActionName, Call};
use tacos_shared::action::Action;
use tacos_shared::messages::{ActionState, TargetObservation};
use tacos_shared::scenario::{DOWNWASH_FACTOR, Scenario};
use tacos_shared::{DroneMode, Vec3};

/// The altitude of a goto to a landmark: the take-off altitude, capped below the detection
/// altitude so a drone that visits a place can see a hidden target there.
pub fn inspect_altitude(scenario: &Scenario) -> f64 {
    let l = &scenario.limits;
    l.takeoff_altitude.min(0.8 * l.detection_altitude)
}

/// The points drones other than `drone` hold or are headed for: the goal of a running goto, or
/// where an airborne drone is. (A goto sent in the last status period is not seen yet; callers
/// add the goals they have just accepted.)
pub fn claimed_points(view: &SwarmView, drone: &str, now: Instant) -> Vec<Vec3> {
    view.drones()
        .filter(|e| e.id.as_str() != drone)
        .filter(|e| e.effective_mode(now) != DroneMode::Unavailable)
        .filter_map(|e| {
            let status = e.status.as_ref()?;
            match &status.action {
                Some(p) if matches!(p.state, ActionState::Running { .. }) => {
                    if let Action::Goto { target } = p.action {
                        return Some(target);
                    }
                }
                _ => {}
            }
            status.mode.is_airborne().then_some(status.position)
        })
        .collect()
}

/// Where `drone` is, as its latest status says: the `from` of [`resolve`].
pub fn position_of(view: &SwarmView, drone: &str) -> Option<Vec3> {
    view.drones()
        .find(|e| e.id.as_str() == drone)
        .and_then(|e| e.status.as_ref())
        .map(|s| s.position)
}

/// How far apart two goal points must be, in the downwash-scaled metric (vertical offsets
/// count half): the safety distance, the planner's margin of 0.5 m on each side, and 1 m of
/// slack. Without the slack the goals sit on the planner's boundary, where a neighbour's stale
/// path margin makes the last metre unreachable (seen: a goto timing out 4.0 m from its
/// neighbour's goal).
pub fn goal_spacing(scenario: &Scenario) -> f64 {
    scenario.limits.safety_distance + 2.0
}

fn scaled_distance(a: &Vec3, b: &Vec3) -> f64 {
    let d = a - b;
    (d.x * d.x + d.y * d.y + (d.z / DOWNWASH_FACTOR).powi(2)).sqrt()
}

/// The point itself when no claim is near it; otherwise a free point on rings round it (one
/// spacing out, then two, every 45°) that is inside the bounds and outside every obstacle: on
/// the nearer ring, the one nearest to `from` (where the drone is). The nearest keeps a drone
/// on its own side of the drones already there: the first free point in a fixed order sent the
/// third drone to one car behind the other two, 5 m apart, and the planner (rightly) would not
/// let it squeeze between them, so its goto timed out. The point itself when none is free (the
/// planner then keeps the drones apart).
fn free_spot(base: Vec3, scenario: &Scenario, claimed: &[Vec3], from: Option<Vec3>) -> Vec3 {
    let spacing = goal_spacing(scenario);
    let free = |p: &Vec3| claimed.iter().all(|c| scaled_distance(p, c) >= spacing);
    if free(&base) {
        return base;
    }
    let far = |p: &Vec3| from.map_or(0.0, |f| (p - f).norm());
    (1..=2)
        .filter_map(|ring| {
            (0..8)
                .map(|k| {
                    let angle = f64::from(k) * std::f64::consts::FRAC_PI_4;
                    let r = f64::from(ring) * spacing;
                    base + Vec3::new(r * angle.cos(), r * angle.sin(), 0.0)
                })
                .filter(|p| {
                    free(p)
                        && scenario
                            .world
                            .check_point(p, scenario.limits.drone_radius)
                            .is_ok()
                })
                .min_by(|a, b| far(a).total_cmp(&far(b)))
        })
        .next()
        .unwrap_or(base)
}

/// The order in which a cycle's calls claim their goal points: the gotos by how far each drone
/// is from the point it names, nearest first (the rest keep their order, ahead of the gotos).
/// The nearest drone arrives first, so it takes the place itself and the later ones take free
/// points on their own side. In the plan's order, the farthest of three drones sent to one car
/// took the car's point, the two nearer ones the points between it and the car, and it could
/// not get past them (seen in CI: its goto timed out three times). `from(drone)` is where a
/// drone is, when known.
pub fn nearest_first<'c>(
    calls: &'c [Call],
    scenario: &Scenario,
    visible: &[TargetObservation],
    from: impl Fn(&str) -> Option<Vec3>,
) -> Vec<&'c Call> {
    let distance = |call: &Call| -> f64 {
        match (
            resolve(call, scenario, visible, &[], None),
            from(&call.drone),
        ) {
            (Ok(Action::Goto { target }), Some(at)) => (target - at).norm(),
            (Ok(Action::Goto { .. }), None) => f64::INFINITY,
            _ => -1.0,
        }
    };
    let mut order: Vec<(f64, &Call)> = calls.iter().map(|c| (distance(c), c)).collect();
    order.sort_by(|a, b| a.0.total_cmp(&b.0));
    order.into_iter().map(|(_, c)| c).collect()
}

/// The action a call asks for, or why it names nothing that can be flown to. A goto to a named
/// place keeps clear of the `claimed` points; a goto to an explicit point is flown as given, or
/// refused when it is closer than `goal_spacing` to a claimed point. `from` is where the drone
/// is, when known: of the free points round a claimed place, it gets the nearest.
pub fn resolve(
    call: &Call,
    scenario: &Scenario,
    visible: &[TargetObservation],
    claimed: &[Vec3],
    from: Option<Vec3>,
) -> Result<Action, String> {
    let altitude = inspect_altitude(scenario);
    match call.action {
        ActionName::ArmTakeoff => Ok(Action::ArmTakeoff),
        ActionName::StopTracking => Ok(Action::StopTracking),
        ActionName::Land => Ok(Action::Land),
        ActionName::Hold => Ok(Action::Hold),
        // A named place wins over a point: the call reads (and is logged) as "goto(<name>)",
        // and small models fill "xyz" with filler beside a name.
        ActionName::Goto => match (call.target_name(), call.xyz) {
            (None, Some([x, y, z])) => {
                let target = Vec3::new(x, y, z);
                let spacing = goal_spacing(scenario);
                match claimed
                    .iter()
                    .find(|c| scaled_distance(&target, c) < spacing)
                {
                    Some(c) => Err(format!(
                        "goto({x}, {y}, {z}): another drone holds or is headed for \
                         ({:.1}, {:.1}, {:.1}), {:.1} m from it; choose a point at least \
                         {spacing:.1} m from every other drone (vertical offsets count half)",
                        c.x,
                        c.y,
                        c.z,
                        (target - c).norm()
                    )),
                    None => Ok(Action::Goto { target }),
                }
            }
            (Some(name), _) => {
                let above = |p: &Vec3| Vec3::new(p.x, p.y, p.z + altitude);
                if let Some(l) = scenario.world.landmark(name) {
                    Ok(Action::Goto {
                        target: free_spot(above(&l.position), scenario, claimed, from),
                    })
                } else if let Some(t) = visible.iter().find(|t| t.name == name) {
                    Ok(Action::Goto {
                        target: free_spot(above(&t.position), scenario, claimed, from),
                    })
                } else {
                    let names = scenario
                        .world
                        .landmarks
                        .iter()
                        .map(|l| l.name.as_str())
                        .chain(visible.iter().map(|t| t.name.as_str()));
                    Err(format!(
                        "goto target {name:?} is neither a landmark nor a visible target; {}",
                        match closest_name(name, names) {
                            Some(near) => format!("the closest name is {near}"),
                            None => "name a landmark of the map or a visible target, or give a \
                                     point in \"xyz\""
                                .to_owned(),
                        }
                    ))
                }
            }
            (None, None) => {
                Err("goto needs a landmark name in \"target\" or a point in \"xyz\"".into())
            }
        },
        ActionName::StartTracking => match call.target_name() {
            Some(name) if scenario.targets.iter().any(|t| t.name == name) => {
                Ok(Action::StartTracking {
                    target: name.to_owned(),
                })
            }
            Some(name) => {
                let targets: Vec<&str> = scenario.targets.iter().map(|t| t.name.as_str()).collect();
                Err(format!(
                    "start_tracking: {name:?} is not a target (landmarks cannot be tracked); the \
                     targets of this map: {}",
                    targets.join(", ")
                ))
            }
            None => Err("start_tracking needs a target name".into()),
        },
    }
}

/// The name among `names` a mistyped `wanted` most likely meant: the nearest by edit distance,
/// if it is within a third of the name's length (at least 2 edits).
fn closest_name<'a>(wanted: &str, names: impl Iterator<Item = &'a str>) -> Option<&'a str> {
    let wanted = wanted.to_lowercase();
    let bound = (wanted.chars().count() / 3).max(2);
    names
        .map(|n| (edit_distance(&wanted, &n.to_lowercase()), n))
        .filter(|(d, _)| *d <= bound)
        .min_by_key(|(d, _)| *d)
        .map(|(_, n)| n)
}

/// Levenshtein distance in characters.
fn edit_distance(a: &str, b: &str) -> usize {
    let b: Vec<char> = b.chars().collect();
    let mut row: Vec<usize> = (0..=b.len()).collect();
    for (i, ca) in a.chars().enumerate() {
        let mut diagonal = row[0];
        row[0] = i + 1;
        for (j, cb) in b.iter().enumerate() {
            let above = row[j + 1];
            row[j + 1] = (above + 1)
                .min(row[j] + 1)
                .min(diagonal + usize::from(ca != *cb));
            diagonal = above;
        }
    }
    row[b.len()]
}

#[cfg(test)]
mod tests {
    use super::*;

    fn call(action: ActionName, target: &str, xyz: Option<[f64; 3]>) -> Call {
        Call {
            task: "T1".into(),
            drone: "alfa".into(),
            action,
            target: target.into(),
            xyz,
        }
    }

    #[test]
    fn landmarks_become_points_at_inspection_altitude() {
        let city = Scenario::builtin("city").expect("city");
        let car = city.world.landmark("car_7").expect("car_7").position;
        assert_eq!(
            resolve(
                &call(ActionName::Goto, "car_7", None),
                &city,
                &[],
                &[],
                None
            ),
            Ok(Action::Goto {
                target: Vec3::new(car.x, car.y, 10.0)
            })
        );
        assert_eq!(
            resolve(
                &call(ActionName::Goto, "none", Some([1.0, 2.0, 3.0])),
                &city,
                &[],
                &[],
                None
            ),
            Ok(Action::Goto {
                target: Vec3::new(1.0, 2.0, 3.0)
            })
        );
        assert_eq!(
            resolve(
                &call(ActionName::Goto, "car_7", Some([1.0, 2.0, 3.0])),
                &city,
                &[],
                &[],
                None
            ),
            Ok(Action::Goto {
                target: Vec3::new(car.x, car.y, 10.0)
            }),
            "the name wins, as the call is shown"
        );
        assert!(resolve(&call(ActionName::Goto, "none", None), &city, &[], &[], None).is_err());
        // A name the map lacks is refused with what would do: the name meant, or how to say it.
        let refused = |action, target: &str| {
            resolve(&call(action, target, None), &city, &[], &[], None)
                .err()
                .unwrap_or_default()
        };
        assert!(refused(ActionName::Goto, "atlantis").ends_with(
            "name a landmark of the map or a visible target, or give a point in \"xyz\""
        ));
        assert!(
            refused(ActionName::Goto, "Vila_3").ends_with("the closest name is villa_3"),
            "{}",
            refused(ActionName::Goto, "Vila_3")
        );
        let not_a_target = refused(ActionName::StartTracking, "car_7");
        assert!(
            not_a_target.contains("(landmarks cannot be tracked); the targets of this map: ")
                && not_a_target.contains("van"),
            "{not_a_target}"
        );
        assert!(
            resolve(
                &call(ActionName::StartTracking, "van", None),
                &city,
                &[],
                &[],
                None
            )
            .is_ok()
        );
    }

    #[test]
    fn a_place_another_drone_claims_gives_a_free_point_beside_it() {
        let city = Scenario::builtin("city").expect("city");
        let car = city.world.landmark("car_7").expect("car_7").position;
        let above = Vec3::new(car.x, car.y, 10.0);
        let spacing = goal_spacing(&city);
        let goto = |claimed: &[Vec3]| match resolve(
            &call(ActionName::Goto, "car_7", None),
            &city,
            &[],
            claimed,
            None,
        ) {
            Ok(Action::Goto { target }) => target,
            other => panic!("not a goto: {other:?}"),
        };
        // Unclaimed: the point above the car. A claim far away changes nothing.
        assert_eq!(goto(&[Vec3::new(0.0, 0.0, 10.0)]), above);
        // Claimed by one drone: a point one spacing away, at the same altitude, clear of it.
        let first = goto(&[above]);
        assert!((first - above).norm() > spacing - 1e-9, "{first:?}");
        assert!((first - above).norm() < spacing + 1e-9, "{first:?}");
        assert_eq!(first.z, above.z);
        // Claimed by two: a third point clear of both, and the world allows it.
        let second = goto(&[above, first]);
        assert!(scaled_distance(&second, &above) >= spacing);
        assert!(scaled_distance(&second, &first) >= spacing);
        assert!(
            city.world
                .check_point(&second, city.limits.drone_radius)
                .is_ok()
        );
        // A drone 4 m below the point does not claim it: downwash counts vertical offsets half.
        let below = above - Vec3::new(0.0, 0.0, 4.0);
        assert_ne!(goto(&[below]), above);
        let far_below = above - Vec3::new(0.0, 0.0, 2.0 * spacing);
        assert_eq!(goto(&[far_below]), above);
        // An explicit point is flown as given when it is clear, and refused with the reason
        // when another drone holds it or is headed for it.
        let point = |claimed: &[Vec3]| {
            resolve(
                &call(ActionName::Goto, "none", Some([1.0, 2.0, 10.0])),
                &city,
                &[],
                claimed,
                None,
            )
        };
        let clear = Vec3::new(1.0, 2.0 + spacing, 10.0);
        assert_eq!(
            point(&[clear]),
            Ok(Action::Goto {
                target: Vec3::new(1.0, 2.0, 10.0)
            })
        );
        let held = Vec3::new(1.0, 3.0, 10.0);
        match point(&[clear, held]) {
            Err(why) => assert!(why.contains("(1.0, 3.0, 10.0), 1.0 m from it"), "{why}"),
            other => panic!("a held point was accepted: {other:?}"),
        }
    }

    /// Three drones to one car, the third coming from the far side of the first two: it gets
    /// the free point on its own side, not one it could only reach between them.
    #[test]
    fn of_the_free_points_a_drone_gets_the_one_nearest_to_it() {
        let city = Scenario::builtin("city").expect("city");
        let car = city.world.landmark("car_1").expect("car_1").position;
        let above = Vec3::new(car.x, car.y, 10.0);
        let spacing = goal_spacing(&city);
        let goto = |claimed: &[Vec3], from: Vec3| match resolve(
            &call(ActionName::Goto, "car_1", None),
            &city,
            &[],
            claimed,
            Some(from),
        ) {
            Ok(Action::Goto { target }) => target,
            other => panic!("not a goto: {other:?}"),
        };
        for from in [
            above + Vec3::new(-60.0, -40.0, -10.0),
            above + Vec3::new(50.0, 5.0, -10.0),
            above + Vec3::new(0.0, 70.0, -10.0),
        ] {
            let first = goto(&[above], from);
            let ring: Vec<Vec3> = (0..8)
                .map(|k| {
                    let a = f64::from(k) * std::f64::consts::FRAC_PI_4;
                    above + Vec3::new(spacing * a.cos(), spacing * a.sin(), 0.0)
                })
                .filter(|p| city.world.check_point(p, city.limits.drone_radius).is_ok())
                .collect();
            assert!(ring.iter().any(|p| (p - first).norm() < 1e-9), "{first:?}");
            for p in &ring {
                assert!(
                    (first - from).norm() <= (p - from).norm() + 1e-9,
                    "{p:?} is nearer"
                );
            }
            let second = goto(&[above, first], from);
            assert!(scaled_distance(&second, &above) >= spacing);
            assert!(scaled_distance(&second, &first) >= spacing);
            // Each flies a straight line that passes the others with the room the planner keeps
            // between two drones (half the safety distance and a sixth of it, each).
            let room = city.limits.safety_distance * 4.0 / 3.0;
            assert!(
                clearance(from, first, above) >= room,
                "{first:?} from {from:?}"
            );
            for other in [above, first] {
                let gap = clearance(from, second, other);
                assert!(
                    gap >= room,
                    "{second:?} from {from:?} passes {other:?} at {gap:.2} m"
                );
            }
        }
    }

    #[test]
    fn drones_sent_to_one_place_claim_it_nearest_first_and_none_is_walled_off() {
        // The CI case: alfa, farthest from car_1, listed first.
        let city = Scenario::builtin("city").expect("city");
        let homes = [
            ("alfa", Vec3::new(-50.0, -132.5, 10.0)),
            ("bravo", Vec3::new(30.0, -132.5, 10.0)),
            ("charlie", Vec3::new(-45.0, -132.5, 10.0)),
        ];
        let mut calls: Vec<Call> = homes
            .iter()
            .map(|(d, _)| Call {
                drone: (*d).into(),
                ..call(ActionName::Goto, "car_1", None)
            })
            .collect();
        calls.insert(1, call(ActionName::Land, "none", None));
        let at = |d: &str| homes.iter().find(|(h, _)| *h == d).map(|(_, p)| *p);
        let order: Vec<&str> = nearest_first(&calls, &city, &[], at)
            .into_iter()
            .map(|c| c.drone.as_str())
            .collect();
        assert_eq!(order[1..], ["bravo", "charlie", "alfa"], "{order:?}");
        // Each drone claims in turn; then each flies straight to its point, the nearer ones
        // arriving first: a drone's line must pass the points of those that got there before
        // it with the planner's room.
        let claim = |order: Vec<&Call>| -> Vec<(Vec3, Vec3)> {
            let mut goals: Vec<(Vec3, Vec3)> = Vec::new();
            for c in order {
                let claimed: Vec<Vec3> = goals.iter().map(|(_, g)| *g).collect();
                if let Ok(Action::Goto { target }) = resolve(c, &city, &[], &claimed, at(&c.drone))
                {
                    goals.push((at(&c.drone).expect("home"), target));
                }
            }
            goals
        };
        let room = city.limits.safety_distance * 4.0 / 3.0;
        let walled_off = |goals: &[(Vec3, Vec3)]| -> Option<String> {
            for (from, goal) in goals {
                for (other_from, other) in goals {
                    let earlier = (other - other_from).norm() < (goal - from).norm();
                    let gap = clearance(*from, *goal, *other);
                    if earlier && gap < room {
                        return Some(format!(
                            "{goal:?} from {from:?} passes {other:?} at {gap:.2} m"
                        ));
                    }
                }
            }
            None
        };
        let goals = claim(nearest_first(&calls, &city, &[], at));
        assert_eq!(goals.len(), 3);
        assert_eq!(walled_off(&goals), None);
        // In the plan's order the farthest drone is walled off (what CI saw).
        assert!(walled_off(&claim(calls.iter().collect())).is_some());
    }

    /// The least horizontal distance from `p` to the segment from `a` to `b`.
    fn clearance(a: Vec3, b: Vec3, p: Vec3) -> f64 {
        let flat = |v: Vec3| Vec3::new(v.x, v.y, 0.0);
        let (a, b, p) = (flat(a), flat(b), flat(p));
        let ab = b - a;
        let t = ((p - a).dot(&ab) / ab.norm_squared()).clamp(0.0, 1.0);
        (a + t * ab - p).norm()
    }
}
