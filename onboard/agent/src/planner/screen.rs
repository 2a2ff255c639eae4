//! Constraint screening. In a crowd most of a solve's half-spaces are metres away from where the
//! plan will be, yet each one adds rows and a slack to every interior-point iteration (at the
//! crossing of the 20-drone swap, 240 of them, and the solve's tail with them). So the QP is
//! solved first with the half-spaces the previous plan comes near, the solution is checked
//! against the ones left out, and any it violates are added and the QP solved again; after a
//! second miss every half-space goes in.
//!
//! The answer is the full problem's, not an approximation: an optimum of the smaller problem that
//! satisfies every left-out half-space is feasible for the full one at the same cost (their
//! slacks are zero), and the full one's cost cannot be lower, since the smaller is a relaxation.

use super::plan::Plan;
use super::qp::SegmentConstraint;
use tacos_shared::Vec3;

/// A left-out half-space counts as violated beyond this (metres). Far below the planner's slack
/// tolerance, so a plan reported `Solved` keeps every half-space to within it.
const VIOLATION_TOLERANCE: f64 = 1e-4;

/// More solves than this with a miss, and the next one holds every half-space.
const SCREENED_SOLVES: u32 = 2;

/// Which of a solve's half-spaces the QP holds.
#[derive(Debug, Default)]
pub(super) struct Screen {
    in_qp: Vec<bool>,
    /// Left-out half-spaces the last solution came near (a buffer of `missed`).
    near: Vec<usize>,
    solves: u32,
}

impl Screen {
    /// Starts a solve: a half-space goes in when `warm` (where the drone is expected at a time
    /// from now, from the previous plan) comes within `distance` of its boundary at the
    /// segment's start, middle or end. Without a previous plan every half-space goes in.
    pub(super) fn start(
        &mut self,
        constraints: &[SegmentConstraint],
        warm: Option<&dyn Fn(f64) -> Vec3>,
        dt: f64,
        distance: f64,
    ) {
        self.solves = 0;
        self.in_qp.clear();
        self.in_qp.extend(constraints.iter().map(|c| match warm {
            None => true,
            Some(warm) => [0.0, 0.5, 1.0].iter().any(|f| {
                let t = (c.segment as f64 + f) * dt;
                c.half.signed_distance(&warm(t)) < distance
            }),
        }));
    }

    /// The half-spaces the next QP holds, copied into `out`.
    pub(super) fn chosen(
        &self,
        constraints: &[SegmentConstraint],
        out: &mut Vec<SegmentConstraint>,
    ) {
        out.clear();
        out.extend(
            constraints
                .iter()
                .zip(&self.in_qp)
                .filter(|(_, chosen)| **chosen)
                .map(|(c, _)| *c),
        );
    }

    /// After a solve whose plan is `plan`: true when a left-out half-space is violated. Then the
    /// left-out ones the plan comes within `distance` of (the violated ones among them) are taken
    /// in for the next solve, or all of them after `SCREENED_SOLVES`.
    pub(super) fn missed(
        &mut self,
        constraints: &[SegmentConstraint],
        plan: &Plan,
        distance: f64,
    ) -> bool {
        self.solves += 1;
        self.near.clear();
        // Each segment's points once: a segment has a half-space per neighbour near it.
        let points: Vec<Vec<Vec3>> = (0..plan.steps())
            .map(|k| plan.free_control_points(k))
            .collect();
        let mut missed = false;
        for (i, (c, chosen)) in constraints.iter().zip(&self.in_qp).enumerate() {
            if *chosen {
                continue;
            }
            let closest = closest_approach(c, points.get(c.segment).map_or(&[], Vec::as_slice));
            missed |= closest < -VIOLATION_TOLERANCE;
            if closest < distance {
                self.near.push(i);
            }
        }
        if missed {
            if self.solves >= SCREENED_SOLVES {
                self.in_qp.iter_mut().for_each(|c| *c = true);
            } else {
                self.near.iter().for_each(|&i| self.in_qp[i] = true);
            }
        }
        missed
    }

    /// QP solves since `start`.
    pub(super) fn solves(&self) -> u32 {
        self.solves
    }
}

/// The smallest signed distance of `points` (its segment's free control points) to the
/// half-space's boundary (negative: outside).
fn closest_approach(c: &SegmentConstraint, points: &[Vec3]) -> f64 {
    points
        .iter()
        .map(|p| c.half.signed_distance(p))
        .fold(f64::INFINITY, f64::min)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::planner::constraints::HalfSpace;
    use crate::planner::qp::ConstraintKind;

    fn wall(segment: usize, x: f64) -> SegmentConstraint {
        // Keep x ≤ `x`.
        SegmentConstraint {
            segment,
            half: HalfSpace::new(Vec3::new(-1.0, 0.0, 0.0), -x).expect("unit normal"),
            kind: ConstraintKind::Obstacle(0),
        }
    }

    #[test]
    fn near_half_spaces_go_in_and_far_ones_wait() {
        let constraints = [wall(0, 1.0), wall(0, 50.0), wall(3, 2.0)];
        let warm = |_t: f64| Vec3::zeros();
        let mut screen = Screen::default();
        screen.start(&constraints, Some(&warm), 0.1, 5.0);
        let mut chosen = Vec::new();
        screen.chosen(&constraints, &mut chosen);
        assert_eq!(chosen, vec![constraints[0], constraints[2]]);
        screen.start(&constraints, None, 0.1, 5.0);
        screen.chosen(&constraints, &mut chosen);
        assert_eq!(
            chosen.len(),
            3,
            "without a previous plan every half-space goes in"
        );
    }

    #[test]
    fn a_violated_left_out_half_space_is_taken_in_then_all_are() {
        let constraints = [wall(1, 50.0), wall(1, 0.5), wall(2, 60.0)];
        let warm = |_t: f64| Vec3::zeros();
        let mut screen = Screen::default();
        // Only the far walls are left out... none of them, with a 1 m screen, is near 0.
        screen.start(&constraints, Some(&warm), 0.1, 1.0);
        let mut chosen = Vec::new();
        screen.chosen(&constraints, &mut chosen);
        assert_eq!(chosen, vec![constraints[1]]);
        // A plan at x = 54 m violates the 50 m wall of segment 1, not the 60 m one.
        let far = Plan::hold(0.0, 0.1, 4, Vec3::new(54.0, 0.0, 0.0));
        assert!(screen.missed(&constraints, &far, 1.0));
        screen.chosen(&constraints, &mut chosen);
        assert_eq!(chosen, vec![constraints[0], constraints[1]]);
        // A second miss (x = 70 m, past the 60 m wall) takes every half-space in.
        let farther = Plan::hold(0.0, 0.1, 4, Vec3::new(70.0, 0.0, 0.0));
        assert!(screen.missed(&constraints, &farther, 1.0));
        screen.chosen(&constraints, &mut chosen);
        assert_eq!(chosen.len(), 3);
        assert_eq!(screen.solves(), 2);
        // A plan inside everything misses nothing.
        let still = Plan::hold(0.0, 0.1, 4, Vec3::zeros());
        assert!(!screen.missed(&constraints, &still, 1.0));
    }

    #[test]
    fn points_fixed_by_the_state_do_not_count() {
        // Segment 0's first two points are where the drone is: outside them is not a miss.
        let plan = Plan::integrate(
            0.0,
            0.1,
            Vec3::new(2.0, 0.0, 0.0),
            Vec3::new(-40.0, 0.0, 0.0),
            vec![Vec3::zeros(); 2],
        );
        // Both walls left out: the previous plan was far behind them.
        let warm = |_t: f64| Vec3::new(-100.0, 0.0, 0.0);
        let mut screen = Screen::default();
        let start_outside = [wall(0, 1.95)];
        screen.start(&start_outside, Some(&warm), 0.1, 1.0);
        assert!(!screen.missed(&start_outside, &plan, 1.0));
        let free_points_outside = [wall(0, -5.0)];
        screen.start(&free_points_outside, Some(&warm), 0.1, 1.0);
        assert!(screen.missed(&free_points_outside, &plan, 1.0));
    }
}
