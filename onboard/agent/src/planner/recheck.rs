//! The check a finished solve passes before it is flown, against the neighbours' paths as they
//! are when it finishes (MADER's "recheck", Tordesillas & How 2021).
//!
//! Two drones' separating half-spaces are the same plane only when both solves read the same
//! pair of paths. Solves run concurrently and take time: a neighbour may publish a new path
//! while mine is being solved, built against my path from before my previous solve, and the two
//! new plans then obey different planes with nothing keeping them apart. Measured with the
//! `swap_loop` bench (20 drones, solves landing up to 0.7 s late): two plans 2.6 m apart in the
//! planner's metric for a 3 m safety distance, and a breach between the vehicles.
//!
//! So a finished plan is compared with every neighbour's latest path over the time both cover,
//! and it is not flown when it comes closer than the planes ask for *and* closer than the plan
//! already being flown (which every neighbour that published since has planned against). The
//! drone keeps its current plan and solves again with the paths now held.

use super::constraints::{Downwash, path_point};
use super::{NeighbourPath, Plan};

/// Seconds between the instants compared (half the planner's default step).
const SAMPLE_S: f64 = 0.05;

/// The closest `plan` (held at its last point after it ends) comes to any of `neighbours` (aged
/// to `now`) from `now` to `until`, in `metric`; infinite when there is nothing to compare.
pub fn closest_approach(
    plan: &Plan,
    now: f64,
    until: f64,
    neighbours: &[NeighbourPath],
    metric: &Downwash,
) -> f64 {
    let mut closest = f64::INFINITY;
    let mut t = now;
    while t <= until + 1e-9 {
        let mine = plan.sample(t).position;
        for n in neighbours.iter().filter(|n| n.is_valid()) {
            if let Some(theirs) = path_point(&n.positions, n.dt, n.age_s.max(0.0) + (t - now)) {
                closest = closest.min(metric.distance(&mine, &theirs));
            }
        }
        t += SAMPLE_S;
    }
    closest
}

/// Whether a finished plan may be flown instead of `current`: it keeps `wanted` (the planes'
/// distance) from every neighbour's latest path, or comes no closer to them than `current` does,
/// or `current` has less than `keep_at_least` seconds left.
///
/// That last bound ends a run of refusals before the plan being flown runs out. Past its end
/// the reference stands at its last point, and a vehicle that reaches it at speed brakes on
/// beyond it, where no neighbour expects it. Seen in the 20-drone swap: a drone that refused 71
/// and 90 plans in a row at the crowded centre, and a breach of 1.4–1.5 m with it; a refused
/// plan is not published, so the neighbours go on planning against the old one.
pub fn may_replace(
    new: &Plan,
    current: Option<&Plan>,
    now: f64,
    neighbours: &[NeighbourPath],
    metric: &Downwash,
    wanted: f64,
    keep_at_least: f64,
) -> bool {
    let until = new.end_time();
    let new_closest = closest_approach(new, now, until, neighbours, metric);
    if new_closest >= wanted {
        return true;
    }
    // Both over the new plan's span, the current one held at its end as it would be flown.
    current.is_none_or(|current| {
        current.end_time() - now < keep_at_least
            || new_closest >= closest_approach(current, now, until, neighbours, metric)
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::{DroneId, Vec3};

    const DT: f64 = 0.1;
    const STEPS: usize = 20;

    /// A plan from `from` at constant `velocity`, starting at `start`.
    fn cruise(start: f64, from: Vec3, velocity: Vec3) -> Plan {
        Plan::integrate(start, DT, from, velocity, vec![Vec3::zeros(); STEPS])
    }

    /// A neighbour's path published `age_s` ago: from `from` at `velocity`.
    fn neighbour(from: Vec3, velocity: Vec3, age_s: f64) -> NeighbourPath {
        NeighbourPath {
            id: DroneId::new("bravo").expect("valid id"),
            positions: cruise(0.0, from, velocity).positions,
            dt: DT,
            age_s,
            avoids: true,
        }
    }

    #[test]
    fn the_closest_approach_reads_both_at_the_same_instants() {
        let metric = Downwash::new(2.0);
        // Head-on along x at 10 m: mine from 0 eastwards at 5 m/s, theirs from 20 m westwards
        // at 5 m/s, published 1 s ago (so it is at 15 m now): they meet 1.5 s from now.
        let mine = cruise(10.0, Vec3::new(0.0, 0.0, 10.0), Vec3::new(5.0, 0.0, 0.0));
        let theirs = neighbour(Vec3::new(20.0, 2.0, 10.0), Vec3::new(-5.0, 0.0, 0.0), 1.0);
        let closest = closest_approach(&mine, 10.0, 12.0, std::slice::from_ref(&theirs), &metric);
        assert!((closest - 2.0).abs() < 1e-9, "{closest}");
        // Read as fresh, their path would be 5 m further and the meeting later; still 2 m.
        let fresh = NeighbourPath {
            age_s: 0.0,
            ..theirs
        };
        let at_fresh = closest_approach(&mine, 10.0, 10.5, &[fresh], &metric);
        assert!(at_fresh > 10.0, "{at_fresh}");
        // Vertical offsets count half.
        let above = neighbour(Vec3::new(0.0, 0.0, 14.0), Vec3::zeros(), 0.0);
        let hold = Plan::hold(0.0, DT, STEPS, Vec3::new(0.0, 0.0, 10.0));
        let vertical = closest_approach(&hold, 0.0, 2.0, &[above], &metric);
        assert!((vertical - 2.0).abs() < 1e-9, "{vertical}");
        // Nothing to compare: infinitely far.
        assert_eq!(
            closest_approach(&hold, 0.0, 2.0, &[], &metric),
            f64::INFINITY
        );
    }

    #[test]
    fn a_plan_closer_than_the_planes_and_the_current_plan_is_not_flown() {
        let metric = Downwash::new(2.0);
        let wanted = 4.0;
        let now = 0.0;
        // The neighbour stands 6 m east of me.
        let bravo = [neighbour(Vec3::new(6.0, 0.0, 10.0), Vec3::zeros(), 0.0)];
        let here = Vec3::new(0.0, 0.0, 10.0);
        let current = Plan::hold(now, DT, STEPS, here);
        // Towards it at 2 m/s: 2 m away after 2 s.
        let closing = cruise(now, here, Vec3::new(2.0, 0.0, 0.0));
        // Whether `new` replaces `current` when refusals end with `keep_at_least` s left.
        let flown = |new: &Plan, current: Option<&Plan>, keep_at_least: f64| {
            may_replace(new, current, now, &bravo, &metric, wanted, keep_at_least)
        };
        assert!(!flown(&closing, Some(&current), 0.0));
        // Away from it, or past it with room: flown.
        let away = cruise(now, here, Vec3::new(-2.0, 0.0, 0.0));
        assert!(flown(&away, Some(&current), 0.0));
        let slow = cruise(now, here, Vec3::new(0.5, 0.0, 0.0));
        assert!(flown(&slow, Some(&current), 0.0));
        // With no plan flown yet, nothing better to keep.
        assert!(flown(&closing, None, 0.0));
        // A current plan that is itself closer (a crowd pressing in): the new one is flown
        // even though it does not keep the planes' distance.
        let worse = cruise(now, here, Vec3::new(2.5, 0.0, 0.0));
        assert!(flown(&closing, Some(&worse), 0.0));
        // The current plan is compared as it would be flown: held at its end (here 1 m from
        // the neighbour, closer than the new one comes).
        let ended = cruise(
            now - 5.0,
            Vec3::new(3.0, 0.0, 10.0),
            Vec3::new(1.0, 0.0, 0.0),
        );
        assert!(flown(&closing, Some(&ended), 0.0));
        // A current plan about to run out is kept no longer: 0.5 s left of a hold here, which
        // keeps away from bravo, and the closing plan is flown once less than 1 s is left.
        let running_out = Plan::hold(now - 1.5, DT, STEPS, here);
        assert!(!flown(&closing, Some(&running_out), 0.4));
        assert!(flown(&closing, Some(&running_out), 1.0));
    }
}
