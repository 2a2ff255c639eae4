//! Where the planner's QP keeps each variable, and the affine expressions of them (velocities,
//! control points) that its cost and rows are written in.

use tacos_shared::Vec3;

/// Most blocks an [`Affine`] combines: a velocity reads two positions and an acceleration.
const AFFINE_TERMS: usize = 3;

/// An affine expression of a 3-vector: `constant + Σ coeff × x[block..block+3]`, each block at
/// most once.
#[derive(Debug, Clone, Copy)]
pub(super) struct Affine {
    terms: [(usize, f64); AFFINE_TERMS],
    len: usize,
    pub(super) constant: Vec3,
}

impl Affine {
    pub(super) fn constant(c: Vec3) -> Affine {
        Affine {
            terms: [(0, 0.0); AFFINE_TERMS],
            len: 0,
            constant: c,
        }
    }
    /// Adds `coeff × block`. Every expression the QP builds has at most `AFFINE_TERMS`
    /// distinct blocks (a debug assertion checks it).
    pub(super) fn with(mut self, block: usize, coeff: f64) -> Affine {
        debug_assert!(self.terms().iter().all(|t| t.0 != block));
        debug_assert!(self.len < AFFINE_TERMS, "more than {AFFINE_TERMS} blocks");
        if self.len < AFFINE_TERMS {
            self.terms[self.len] = (block, coeff);
            self.len += 1;
        }
        self
    }
    pub(super) fn terms(&self) -> &[(usize, f64)] {
        &self.terms[..self.len]
    }
}

#[derive(Debug, Clone, Copy)]
pub(super) struct Layout {
    pub(super) k: usize,
    pub(super) groups: usize,
}

impl Layout {
    /// Block of p_k, k ≥ 1.
    pub(super) fn p(&self, k: usize) -> usize {
        3 * (k - 1)
    }
    /// Block of a_k, k < K.
    pub(super) fn a(&self, k: usize) -> usize {
        3 * self.k + 3 * k
    }
    pub(super) fn slack(&self, g: usize) -> usize {
        6 * self.k + g
    }
    pub(super) fn workspace_slack(&self) -> usize {
        6 * self.k + self.groups
    }
    pub(super) fn floor_slack(&self) -> usize {
        6 * self.k + self.groups + 1
    }
    pub(super) fn n(&self) -> usize {
        6 * self.k + self.groups + 2
    }

    /// The velocity at knot k ≥ 1, `(p_k − p_{k−1}) / dt + a_{k−1} dt / 2` (`p_0` the current
    /// position).
    pub(super) fn velocity(&self, k: usize, p0: &Vec3, dt: f64) -> Affine {
        let v = Affine::constant(Vec3::zeros())
            .with(self.p(k), 1.0 / dt)
            .with(self.a(k - 1), dt / 2.0);
        if k == 1 {
            Affine {
                constant: -p0 / dt,
                ..v
            }
        } else {
            v.with(self.p(k - 1), -1.0 / dt)
        }
    }

    /// The control points of segment k as affine expressions (see `Plan::control_points`).
    pub(super) fn control_points(&self, seg: usize, p0: &Vec3, v0: &Vec3, dt: f64) -> Vec<Affine> {
        if seg == 0 {
            let h = dt / 2.0;
            vec![
                Affine::constant(*p0),
                Affine::constant(p0 + v0 * (h / 2.0)),
                Affine::constant(p0 + v0 * h).with(self.a(0), 0.5 * h * h),
                Affine::constant(p0 + v0 * (1.5 * h)).with(self.a(0), h * h),
                Affine::constant(Vec3::zeros()).with(self.p(1), 1.0),
            ]
        } else {
            // The middle point p_k + v_k dt / 2, with v_k read forward from the segment's own
            // variables: (p_{k+1} − p_k) / dt − a_k dt / 2.
            vec![
                Affine::constant(Vec3::zeros()).with(self.p(seg), 1.0),
                Affine::constant(Vec3::zeros())
                    .with(self.p(seg), 0.5)
                    .with(self.p(seg + 1), 0.5)
                    .with(self.a(seg), -dt * dt / 4.0),
                Affine::constant(Vec3::zeros()).with(self.p(seg + 1), 1.0),
            ]
        }
    }
}
