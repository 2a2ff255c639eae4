//! Closed-loop benchmark of the distributed planner: the antipodal swap through the city's
//! business district. N drones on a circle of radius 60 m around the four skyscrapers, at
//! 10–20 m, each flies to the opposite point of the circle. Every drone replans at 20 Hz
//! against the others' previous paths (range-filtered, age one period) and follows its plan
//! perfectly in between. Each `plan()` call is timed; safety is checked on dense samples.
//!
//! Prints one line per N (6, 12, 20), the N = 20 line last. No assertions on speed.
//! `PLANNER_BENCH_PERIOD_S=0.25` replans every 250 ms instead (a planner starved of CPU, as
//! 20 onboards on two cores are where the swap crosses). `PLANNER_BENCH_SCREEN_M=1e9` screens no
//! half-space out of the first QP (see `planner/screen.rs`), any other value sets the distance.
//!
//! `cargo bench -p tacos-onboard --bench planner` (release), or in the dev profile:
//! `cargo build -p tacos-onboard --benches` then run `target/debug/deps/planner-*`.

use std::time::Instant;
use tacos_onboard::planner::{
    Goal, NeighbourPath, PlanStatus, Planner, PlannerConfig, neighbours_in_range,
};
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, Vec3};

const RADIUS: f64 = 60.0;
/// Seconds between solves; `PLANNER_BENCH_PERIOD_S` overrides it (a starved planner).
const REPLAN: f64 = 0.05;
const DENSE: usize = 10;
const MAX_SIM: f64 = 120.0;
const ARRIVED: f64 = 1.0;

struct Outcome {
    solve_ms: Vec<f64>,
    min_pair: f64,
    min_clearance: f64,
    arrived: usize,
    sim_s: f64,
    relaxed: usize,
    braking: usize,
    max_slack: f64,
    iterations: Vec<u32>,
    constraints: Vec<usize>,
    in_qp: Vec<usize>,
    qp_solves: usize,
    solver_reuses: u64,
}

fn run(n: usize, scenario: &Scenario, replan: f64, screen: Option<f64>) -> Result<Outcome, String> {
    let mut cfg = PlannerConfig::from_scenario(&scenario.limits, &scenario.world);
    if let Some(screen) = screen {
        cfg.screen_distance = screen;
    }
    let mut planners = (0..n)
        .map(|_| Planner::new(cfg.clone()))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())?;
    let ids = (0..n)
        .map(|i| DroneId::new(format!("d{i}")))
        .collect::<Result<Vec<_>, _>>()
        .map_err(|e| e.to_string())?;
    let starts: Vec<Vec3> = (0..n)
        .map(|i| {
            let angle = std::f64::consts::TAU * i as f64 / n as f64;
            // Altitudes spread over 10–20 m, neighbours on the circle at different heights.
            let altitude = 10.0 + 10.0 * ((i * 7) % n) as f64 / n as f64;
            Vec3::new(RADIUS * angle.cos(), RADIUS * angle.sin(), altitude)
        })
        .collect();
    let goals: Vec<Vec3> = starts.iter().map(|p| Vec3::new(-p.x, -p.y, p.z)).collect();
    let mut state: Vec<(Vec3, Vec3)> = starts.iter().map(|p| (*p, Vec3::zeros())).collect();
    let mut published: Vec<(f64, Vec<Vec3>)> = starts
        .iter()
        .map(|p| (0.0, vec![*p; cfg.horizon_steps + 1]))
        .collect();
    let mut arrived = vec![false; n];
    let mut out = Outcome {
        solve_ms: Vec::new(),
        min_pair: f64::INFINITY,
        min_clearance: f64::INFINITY,
        arrived: 0,
        sim_s: 0.0,
        relaxed: 0,
        braking: 0,
        max_slack: 0.0,
        iterations: Vec::new(),
        constraints: Vec::new(),
        in_qp: Vec::new(),
        qp_solves: 0,
        solver_reuses: 0,
    };
    let mut now = 0.0;
    let mut dense = vec![Vec::with_capacity(DENSE); n];
    while now < MAX_SIM && arrived.iter().any(|a| !a) {
        let mut plans = Vec::with_capacity(n);
        for i in 0..n {
            let others = (0..n).filter(|&j| j != i).map(|j| NeighbourPath {
                id: ids[j].clone(),
                positions: published[j].1.clone(),
                dt: cfg.dt,
                age_s: now - published[j].0,
                avoids: true,
            });
            let near = neighbours_in_range(state[i].0, others, cfg.neighbour_range);
            let goal = Goal::fixed(goals[i]);
            let started = Instant::now();
            let result = planners[i].plan(now, state[i].0, state[i].1, &goal, &near);
            out.solve_ms.push(started.elapsed().as_secs_f64() * 1e3);
            let result = result.map_err(|e| e.to_string())?;
            out.iterations.push(result.iterations);
            out.constraints.push(planners[i].last_constraints().len());
            out.in_qp.push(result.qp_constraints);
            out.qp_solves += result.qp_solves as usize;
            match result.status {
                PlanStatus::Solved => {}
                PlanStatus::Relaxed { max_slack } => {
                    out.relaxed += 1;
                    out.max_slack = out.max_slack.max(max_slack);
                }
                PlanStatus::Braking(_) => out.braking += 1,
            }
            plans.push(result.plan);
        }
        // What is flown until the next solve, densely.
        for (i, plan) in plans.iter().enumerate() {
            dense[i].clear();
            for s in 0..=DENSE {
                dense[i].push(plan.sample(now + replan * s as f64 / DENSE as f64).position);
            }
        }
        for s in 0..=DENSE {
            for i in 0..n {
                let p = dense[i][s];
                for o in &scenario.world.obstacles {
                    out.min_clearance = out.min_clearance.min(o.clearance_lower_bound(&p));
                }
                for other in dense.iter().skip(i + 1) {
                    out.min_pair = out.min_pair.min((p - other[s]).norm());
                }
            }
        }
        for (i, plan) in plans.iter().enumerate() {
            published[i] = (now, plan.path().to_vec());
        }
        now += replan;
        for (i, plan) in plans.iter().enumerate() {
            let s = plan.sample(now);
            state[i] = (s.position, s.velocity);
            if (s.position - goals[i]).norm() < ARRIVED {
                arrived[i] = true;
            }
        }
    }
    out.arrived = arrived.iter().filter(|a| **a).count();
    out.solver_reuses = planners.iter().map(|p| p.solver_reuses()).sum();
    out.sim_s = now;
    Ok(out)
}

fn percentile(sorted: &[f64], q: f64) -> f64 {
    if sorted.is_empty() {
        return f64::NAN;
    }
    let i = ((sorted.len() - 1) as f64 * q).round() as usize;
    sorted[i.min(sorted.len() - 1)]
}

/// `p50=… p95=… max=…` of `values`.
fn spread(values: impl Iterator<Item = f64>) -> String {
    let mut sorted: Vec<f64> = values.collect();
    sorted.sort_by(f64::total_cmp);
    format!(
        "p50={} p95={} max={}",
        percentile(&sorted, 0.5),
        percentile(&sorted, 0.95),
        sorted.last().copied().unwrap_or(f64::NAN)
    )
}

fn main() {
    let scenario = match Scenario::builtin("city") {
        Ok(s) => s,
        Err(e) => {
            eprintln!("planner bench: the city scenario: {e}");
            std::process::exit(1);
        }
    };
    let replan = std::env::var("PLANNER_BENCH_PERIOD_S")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|p| p.is_finite() && *p > 0.0)
        .unwrap_or(REPLAN);
    let screen = std::env::var("PLANNER_BENCH_SCREEN_M")
        .ok()
        .and_then(|s| s.parse::<f64>().ok())
        .filter(|d| d.is_finite() && *d >= 0.0);
    for n in [6, 12, 20] {
        let out = match run(n, &scenario, replan, screen) {
            Ok(o) => o,
            Err(e) => {
                eprintln!("planner bench N={n}: {e}");
                std::process::exit(1);
            }
        };
        let mut sorted = out.solve_ms.clone();
        sorted.sort_by(f64::total_cmp);
        let mean = sorted.iter().sum::<f64>() / sorted.len().max(1) as f64;
        println!(
            "  N={n}: solves={} mean_ms={mean:.3} max_ms={:.3} iterations {} half-spaces {} in_qp {} qp_solves={} solver_reuses={} relaxed={} braking={} max_slack_m={:.3}",
            sorted.len(),
            sorted.last().copied().unwrap_or(f64::NAN),
            spread(out.iterations.iter().map(|&i| f64::from(i))),
            spread(out.constraints.iter().map(|&c| c as f64)),
            spread(out.in_qp.iter().map(|&c| c as f64)),
            out.qp_solves,
            out.solver_reuses,
            out.relaxed,
            out.braking,
            out.max_slack,
        );
        println!(
            "planner N={n} p50_ms={:.3} p95_ms={:.3} rate_hz={:.1} min_pair_m={:.3} min_clearance_m={:.3} arrived={}/{n} sim_s={:.2}",
            percentile(&sorted, 0.5),
            percentile(&sorted, 0.95),
            1e3 / mean,
            out.min_pair,
            out.min_clearance,
            out.arrived,
            out.sim_s,
        );
    }
}
