//! The planner's quadratic programme in clarabel's form
//! `min ½ xᵀPx + qᵀx  s.t.  Ax + s = b, s ∈ K`, built as sparse CSC matrices.
//!
//! Variables, for K steps and G slack groups:
//! `[p_1..p_K | a_0..a_{K-1} | σ_1..σ_G | σ_ws | σ_floor]` (3K + 3K + G + 2).
//! `p_0`, `v_0` are the current state (constants). The velocities are not variables: with
//! piecewise-constant acceleration, `v_k = (p_k − p_{k−1}) / dt + a_{k−1} dt / 2`, an affine
//! expression of three variables (see `Layout::velocity`), and the double integrator is
//! `p_{k+1} − 2 p_k + p_{k−1} = (a_k + a_{k−1}) dt² / 2`. The problem is the one with `v_k` as
//! variables and `v_{k+1} = v_k + dt a_k` as rows, in 3K fewer variables and 3K fewer rows (a
//! smaller KKT system at every interior-point iteration). Velocities rather than
//! accelerations are the ones eliminated: `a_k = (v_{k+1} − v_k) / dt` would put `1 / dt²` in
//! the jerk's cost, and the solver, at the same tolerances, returned plans centimetres to
//! decimetres from the exact ones. Rows:
//! - zero cone: the double-integrator dynamics (3K rows);
//! - non-negative cone: σ ≥ 0, the half-spaces (each group: every non-constant control point of
//!   its segment, relaxed by its own σ), the shrunk workspace box's walls and ceiling (relaxed
//!   by one σ_ws) and its floor (relaxed by σ_floor, priced far above the rest: see
//!   `QpInput::floor_slack_weight`);
//! - second-order cones: `‖v_k‖ ≤ v̄_k` (k = 1..K) and `‖a_k‖ ≤ ā` (k = 0..K-1). The norm
//!   bounds are exact (clarabel takes second-order cones natively), not polyhedral.
//!
//! Speed is bounded at the knots only; with piecewise-constant acceleration the velocity is
//! linear in between, so its norm (convex) is bounded by the larger of the two ends.

use super::constraints::HalfSpace;
use super::reachable::Reachable;
use clarabel::algebra::CscMatrix;
use clarabel::solver::{DefaultSettings, DefaultSolver, IPSolver, SolverStatus, SupportedConeT};
use tacos_shared::Vec3;

mod layout;
use layout::{Affine, Layout};

/// Weights of the cost (all per step, squared norms).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CostWeights {
    /// Position error to the reference at every step.
    pub position: f64,
    /// Extra position weight at the last step.
    pub terminal_position: f64,
    /// Velocity error to the reference velocity at every step.
    pub velocity: f64,
    /// Extra velocity weight at the last step.
    pub terminal_velocity: f64,
    /// ‖a_k‖².
    pub acceleration: f64,
    /// ‖a_k − a_{k−1}‖² (a_{−1}: the previous plan's acceleration now).
    pub jerk: f64,
}

/// One linear constraint on one segment: all of the segment's control points inside `half`.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentConstraint {
    pub segment: usize,
    pub half: HalfSpace,
    pub kind: ConstraintKind,
}

#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ConstraintKind {
    /// Index into the planner's obstacle list.
    Obstacle(usize),
    /// Index into the neighbour slice given to `plan`.
    Neighbour(usize),
}

pub(crate) struct QpInput<'a> {
    pub dt: f64,
    pub p0: Vec3,
    pub v0: Vec3,
    pub a_prev: Vec3,
    /// Reference positions for p_1..p_K.
    pub reference: &'a [Vec3],
    /// Reference velocity for v_1..v_K.
    pub velocity_reference: Vec3,
    /// Speed bounds for v_1..v_K.
    pub speed_bounds: &'a [f64],
    /// `v_z ≤ climb_bound` and `−v_z ≤ descent_bound` for v_1..v_K.
    pub climb_bound: f64,
    pub descent_bound: f64,
    pub max_accel: f64,
    /// Workspace box for every non-constant control point.
    pub box_lo: Vec3,
    pub box_hi: Vec3,
    /// Where each segment's control points can be: a workspace wall they cannot leave is not
    /// written as rows.
    pub reachable: &'a Reachable,
    pub constraints: &'a [SegmentConstraint],
    pub weights: CostWeights,
    /// Price per metre of each obstacle or neighbour constraint's slack (one per segment).
    pub slack_weight: f64,
    /// Price per metre of the walls' and ceiling's slack, which is shared by every segment.
    pub workspace_slack_weight: f64,
    /// Price per metre of the floor's slack: the ground is the one obstacle that is always
    /// there, and going into it is a crash, so it must cost more than giving up separation.
    pub floor_slack_weight: f64,
}

#[derive(Debug, Clone, PartialEq)]
pub(crate) struct QpOutput {
    pub accelerations: Vec<Vec3>,
    /// One per constraint, metres.
    pub slacks: Vec<f64>,
    pub workspace_slack: f64,
    pub floor_slack: f64,
    pub iterations: u32,
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum QpError {
    #[error("the solver rejected the problem: {0}")]
    Setup(String),
    #[error("the solver stopped with status {0}")]
    Status(String),
    #[error("the solver returned non-finite values")]
    NonFinite,
}

/// Triplet buffers kept between solves, and the last solver (see `last`).
#[derive(Default)]
pub(crate) struct QpWorkspace {
    p_i: Vec<usize>,
    p_j: Vec<usize>,
    p_v: Vec<f64>,
    q: Vec<f64>,
    a_i: Vec<usize>,
    a_j: Vec<usize>,
    a_v: Vec<f64>,
    b: Vec<f64>,
    settings: Option<DefaultSettings<f64>>,
    /// The last solve's solver, with the shape of its problem: a solve of the same shape (the
    /// same sparsity and cones, as when no half-space is near) updates its data instead of
    /// setting a solver up again (a quarter of a solve: KKT assembly, AMD ordering,
    /// equilibration). The equilibration of the first problem of the shape is kept.
    last: Option<(Shape, DefaultSolver<f64>)>,
    /// Solves that reused the last solver.
    reuses: u64,
}

/// What a solver can be reused for: the dimensions and the cones (the sparsity of P and A is
/// checked by clarabel's own data update).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
struct Shape {
    n: usize,
    m: usize,
    zero_rows: usize,
    nonneg_rows: usize,
}

impl std::fmt::Debug for QpWorkspace {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("QpWorkspace")
            .field("rows", &self.b.len())
            .field("last_shape", &self.last.as_ref().map(|(shape, _)| shape))
            .finish_non_exhaustive()
    }
}

impl QpWorkspace {
    fn settings(&mut self) -> DefaultSettings<f64> {
        self.settings
            .get_or_insert_with(|| DefaultSettings {
                verbose: false,
                max_iter: 60,
                presolve_enable: false,
                // In the planner's units: a cost gap of 1e-4 (the cost is squared metres, and
                // a metre of slack costs 2e4) and residuals of 1e-6 of the data's norms
                // (metres, tens of them). Two iterations fewer per solve than 1e-6 / 1e-7 in the
                // 20-drone swap (p50 11 → 9), the same clearances; any plan still keeps its
                // half-spaces to within a tenth of the planner's millimetre slack tolerance.
                tol_gap_abs: 1e-4,
                tol_gap_rel: 1e-4,
                tol_feas: 1e-6,
                // The KKT systems are small and well regularised: iterative refinement of each
                // KKT solve took a third of the solve time in the planner bench's 20-drone
                // swap (mean 4.5 → 3.0 ms, p95 12 → 7.6 ms without it), with the same
                // iterations, no braking and the same clearances. The solver's own residual
                // checks still decide when a solve has converged.
                iterative_refinement_enable: false,
                ..DefaultSettings::default()
            })
            .clone()
    }

    /// Solves that reused the last solver (see `last`).
    pub(crate) fn reuses(&self) -> u64 {
        self.reuses
    }

    fn cost(&mut self, i: usize, j: usize, v: f64) {
        // Upper triangle only.
        let (i, j) = if i <= j { (i, j) } else { (j, i) };
        self.p_i.push(i);
        self.p_j.push(j);
        self.p_v.push(v);
    }

    /// Adds `weight × ‖e‖²` to the cost `½ xᵀPx + qᵀx` (dropping its constant).
    fn cost_square(&mut self, weight: f64, e: &Affine) {
        let terms = e.terms();
        for axis in 0..3 {
            for (t, &(bi, ci)) in terms.iter().enumerate() {
                let i = bi + axis;
                self.q[i] += 2.0 * weight * ci * e.constant[axis];
                self.cost(i, i, 2.0 * weight * ci * ci);
                for &(bj, cj) in &terms[t + 1..] {
                    self.cost(i, bj + axis, 2.0 * weight * ci * cj);
                }
            }
        }
    }

    /// The constraint matrix in CSC form, by a counting sort on the column: rows are added in
    /// increasing order and never repeat a (row, column) pair, so each column's rows come out
    /// sorted, without the comparison sort of `CscMatrix::new_from_triplets`.
    fn constraint_matrix(&self, m: usize, n: usize) -> CscMatrix<f64> {
        debug_assert!(self.a_i.windows(2).all(|w| w[0] <= w[1]));
        let mut colptr = vec![0; n + 1];
        for &col in &self.a_j {
            colptr[col + 1] += 1;
        }
        for col in 0..n {
            colptr[col + 1] += colptr[col];
        }
        let mut next = colptr.clone();
        let mut rowval = vec![0; self.a_i.len()];
        let mut nzval = vec![0.0; self.a_i.len()];
        for ((&row, &col), &v) in self.a_i.iter().zip(&self.a_j).zip(&self.a_v) {
            rowval[next[col]] = row;
            nzval[next[col]] = v;
            next[col] += 1;
        }
        CscMatrix::new(m, n, colptr, rowval, nzval)
    }

    fn entry(&mut self, row: usize, col: usize, v: f64) {
        self.a_i.push(row);
        self.a_j.push(col);
        self.a_v.push(v);
    }

    /// Adds the row `normal·point ≤ bound` (plus `extra` terms) as a non-negative-cone row.
    fn le_row(
        &mut self,
        row: &mut usize,
        normal: &Vec3,
        point: &Affine,
        bound: f64,
        extra: &[(usize, f64)],
    ) {
        for &(block, coeff) in point.terms() {
            for axis in 0..3 {
                let c = normal[axis] * coeff;
                if c != 0.0 {
                    self.entry(*row, block + axis, c);
                }
            }
        }
        for &(col, c) in extra {
            self.entry(*row, col, c);
        }
        self.b.push(bound - normal.dot(&point.constant));
        *row += 1;
    }

    pub(crate) fn solve(&mut self, input: &QpInput<'_>) -> Result<QpOutput, QpError> {
        let k = input.reference.len();
        // The QP is written in coordinates centred on the drone (`origin`): its cost is then the
        // size of the errors, not of the drone's distance from the map's origin, and the
        // solver's relative gap tolerance means the same at every point of the map.
        let origin = input.p0;
        let p0 = Vec3::zeros();
        let (box_lo, box_hi) = (input.box_lo - origin, input.box_hi - origin);
        let dt = input.dt;
        let layout = Layout {
            k,
            groups: input.constraints.len(),
        };
        let n = layout.n();
        for buf in [&mut self.p_i, &mut self.p_j, &mut self.a_i, &mut self.a_j] {
            buf.clear();
        }
        for buf in [&mut self.p_v, &mut self.a_v, &mut self.b] {
            buf.clear();
        }
        self.q.clear();
        self.q.resize(n, 0.0);

        // ---- cost ----
        let w = input.weights;
        for step in 1..=k {
            let last = step == k;
            let wp = w.position + if last { w.terminal_position } else { 0.0 };
            let wv = w.velocity + if last { w.terminal_velocity } else { 0.0 };
            let g = input.reference[step - 1] - origin;
            for axis in 0..3 {
                let ip = layout.p(step) + axis;
                self.cost(ip, ip, 2.0 * wp);
                self.q[ip] -= 2.0 * wp * g[axis];
            }
            let mut velocity_error = layout.velocity(step, &p0, dt);
            velocity_error.constant -= input.velocity_reference;
            self.cost_square(wv, &velocity_error);
        }
        for step in 0..k {
            for axis in 0..3 {
                let ia = layout.a(step) + axis;
                self.cost(ia, ia, 2.0 * (w.acceleration + w.jerk));
                if step == 0 {
                    self.q[ia] -= 2.0 * w.jerk * input.a_prev[axis];
                } else {
                    let prev = layout.a(step - 1) + axis;
                    self.cost(prev, prev, 2.0 * w.jerk);
                    self.cost(prev, ia, -2.0 * w.jerk);
                }
            }
        }
        for g in 0..layout.groups {
            self.q[layout.slack(g)] = input.slack_weight;
        }
        self.q[layout.workspace_slack()] = input.workspace_slack_weight;
        self.q[layout.floor_slack()] = input.floor_slack_weight;

        // ---- zero cone: dynamics ----
        let mut row = 0;
        let half_dt2 = 0.5 * dt * dt;
        for axis in 0..3 {
            // p_1 − a_0 dt²/2 = p_0 + v_0 dt
            self.entry(row, layout.p(1) + axis, 1.0);
            self.entry(row, layout.a(0) + axis, -half_dt2);
            self.b.push(p0[axis] + dt * input.v0[axis]);
            row += 1;
        }
        for step in 1..k {
            for axis in 0..3 {
                // p_{k+1} − 2 p_k + p_{k−1} − (a_k + a_{k−1}) dt²/2 = 0
                self.entry(row, layout.p(step + 1) + axis, 1.0);
                self.entry(row, layout.p(step) + axis, -2.0);
                if step > 1 {
                    self.entry(row, layout.p(step - 1) + axis, 1.0);
                }
                self.entry(row, layout.a(step) + axis, -half_dt2);
                self.entry(row, layout.a(step - 1) + axis, -half_dt2);
                self.b.push(if step == 1 { -p0[axis] } else { 0.0 });
                row += 1;
            }
        }
        let zero_rows = row;

        // ---- non-negative cone ----
        // Every σ: the groups', then σ_ws and σ_floor, which follow them.
        for g in 0..layout.groups + 2 {
            // σ ≥ 0  ⇔  −σ ≤ 0
            self.entry(row, layout.slack(g), -1.0);
            self.b.push(0.0);
            row += 1;
        }
        for (g, c) in input.constraints.iter().enumerate() {
            // normal·x + σ ≥ offset  ⇔  (−normal)·x − σ ≤ −offset
            let neg = -c.half.normal;
            for point in layout.control_points(c.segment, &p0, &input.v0, dt) {
                if point.terms().is_empty() {
                    continue; // fixed by the current state
                }
                self.le_row(
                    &mut row,
                    &neg,
                    &point,
                    -(c.half.offset - c.half.normal.dot(&origin)),
                    &[(layout.slack(g), -1.0)],
                );
            }
        }
        let ws = layout.workspace_slack();
        let floor = layout.floor_slack();
        for seg in 0..k {
            let points = layout.control_points(seg, &p0, &input.v0, dt);
            // Skip the first point of segments ≥ 1: it is the last of the previous one.
            let skip = if seg == 0 { 0 } else { 1 };
            for point in points.iter().skip(skip) {
                if point.terms().is_empty() {
                    continue;
                }
                for axis in 0..3 {
                    let e = Vec3::ith(axis, 1.0);
                    // The walls in the world's coordinates, as the reachable balls are.
                    let below_hi = HalfSpace {
                        normal: -e,
                        offset: -input.box_hi[axis],
                    };
                    let above_lo = HalfSpace {
                        normal: e,
                        offset: input.box_lo[axis],
                    };
                    if !input.reachable.keeps_inside(&below_hi, seg) {
                        self.le_row(&mut row, &e, point, box_hi[axis], &[(ws, -1.0)]);
                    }
                    if !input.reachable.keeps_inside(&above_lo, seg) {
                        let slack = if axis == 2 { floor } else { ws };
                        self.le_row(&mut row, &(-e), point, -box_lo[axis], &[(slack, -1.0)]);
                    }
                }
            }
        }
        let up = Vec3::z();
        for step in 1..=k {
            let v = layout.velocity(step, &p0, dt);
            self.le_row(&mut row, &up, &v, input.climb_bound, &[]);
            self.le_row(&mut row, &(-up), &v, input.descent_bound, &[]);
        }
        let nonneg_rows = row - zero_rows;

        // ---- second-order cones ----
        let mut cones = vec![
            SupportedConeT::ZeroConeT(zero_rows),
            SupportedConeT::NonnegativeConeT(nonneg_rows),
        ];
        for step in 1..=k {
            let bound = input.speed_bounds.get(step - 1).copied().unwrap_or(0.0);
            self.b.push(bound);
            row += 1;
            let v = layout.velocity(step, &p0, dt);
            for axis in 0..3 {
                for &(block, coeff) in v.terms() {
                    self.entry(row, block + axis, -coeff);
                }
                self.b.push(v.constant[axis]);
                row += 1;
            }
            cones.push(SupportedConeT::SecondOrderConeT(4));
        }
        for step in 0..k {
            self.b.push(input.max_accel);
            row += 1;
            for axis in 0..3 {
                self.entry(row, layout.a(step) + axis, -1.0);
                self.b.push(0.0);
                row += 1;
            }
            cones.push(SupportedConeT::SecondOrderConeT(4));
        }
        let m = row;

        if self
            .b
            .iter()
            .chain(&self.q)
            .chain(&self.a_v)
            .chain(&self.p_v)
            .any(|v| !v.is_finite())
        {
            return Err(QpError::Setup("non-finite problem data".into()));
        }
        let p = CscMatrix::new_from_triplets(
            n,
            n,
            self.p_i.clone(),
            self.p_j.clone(),
            self.p_v.clone(),
        );
        let a = self.constraint_matrix(m, n);
        let shape = Shape {
            n,
            m,
            zero_rows,
            nonneg_rows,
        };
        let reused = match self.last.take() {
            Some((last_shape, mut solver)) if last_shape == shape => solver
                .update_data(&p, &self.q, &a, &self.b)
                .is_ok()
                .then_some(solver),
            _ => None,
        };
        let mut solver = match reused {
            Some(solver) => {
                self.reuses += 1;
                solver
            }
            None => {
                let settings = self.settings();
                DefaultSolver::new(&p, &self.q, &a, &self.b, &cones, settings)
                    .map_err(|e| QpError::Setup(e.to_string()))?
            }
        };
        solver.solve();
        let solver = &self.last.insert((shape, solver)).1;
        let sol = &solver.solution;
        match sol.status {
            SolverStatus::Solved | SolverStatus::AlmostSolved => {}
            other => return Err(QpError::Status(format!("{other:?}"))),
        }
        let x = &sol.x;
        if x.len() != n || x.iter().any(|v| !v.is_finite()) {
            return Err(QpError::NonFinite);
        }
        let accelerations = (0..k)
            .map(|step| {
                let i = layout.a(step);
                Vec3::new(x[i], x[i + 1], x[i + 2])
            })
            .collect();
        let slacks = (0..layout.groups)
            .map(|g| x[layout.slack(g)].max(0.0))
            .collect();
        Ok(QpOutput {
            accelerations,
            slacks,
            workspace_slack: x[ws].max(0.0),
            floor_slack: x[layout.floor_slack()].max(0.0),
            iterations: sol.iterations,
        })
    }
}
