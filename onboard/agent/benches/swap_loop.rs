//! The 20-drone antipodal swap through the city's skyscrapers flown the way the processes fly
//! it, in one process and on a simulated clock: each drone's `Motion` (the onboard's own core)
//! starts a solve on its 50 ms timer when none is out, and the solve's plan and path land only
//! after a solve latency (a starved planner on a shared CPU: uniform in [0, max]); the control
//! loop samples the current plan at 50 Hz and tacos-sitl's point mass (PX4's position controller
//! in miniature) tracks it at 100 Hz. Paths reach the others as soon as they are published.
//! Separation is checked on the vehicles, every physics step, as tacos-sitl checks it.
//!
//! Unlike the `planner` bench (every drone solves at once and flies its plan perfectly), this
//! reproduces the asynchrony and the tracking lag of the real loop. One line per solve-latency
//! bound and seed; `SWAP_LOOP_LATENCY_S=0.05,0.25` and `SWAP_LOOP_SEEDS=4` choose them.
//!
//! `cargo build -p tacos-onboard --benches` then `target/debug/deps/swap_loop-*` (the dev
//! profile optimises this crate), or `cargo bench -p tacos-onboard --bench swap_loop`.

use tacos_onboard::motion::{Motion, MotionConfig, SolveDone, Steering};
use tacos_onboard::planner::{Downwash, Goal, PlannerConfig};
use tacos_shared::messages::PathMessage;
use tacos_shared::scenario::Scenario;
use tacos_shared::{DroneId, Vec3};
use tacos_sitl::motion::{MotionLimits, PointMass, Reference};

const N: usize = 20;
const RADIUS: f64 = 60.0;
const PHYSICS_DT: f64 = 0.01;
/// Control ticks every this many physics steps (50 Hz).
const CONTROL_EVERY: usize = 2;
const MAX_SIM: f64 = 90.0;
const ARRIVED: f64 = 1.0;

/// A small deterministic generator (no external crates).
struct Lcg(u64);
impl Lcg {
    fn unit(&mut self) -> f64 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 11) as f64) / ((1u64 << 53) as f64)
    }
}

struct Drone {
    motion: Motion,
    body: PointMass,
    goal: Vec3,
    steering: Steering,
    /// The solve out and when it lands.
    solving: Option<(f64, SolveDone)>,
    next_solve: f64,
    arrived: bool,
}

#[derive(Default)]
struct Outcome {
    min_pair: f64,
    breach_samples: usize,
    first_breach: Option<String>,
    min_clearance: f64,
    obstacle_breach_samples: usize,
    /// Closest pair of the references streamed, in the planner's downwash-scaled metric.
    min_planned_scaled: f64,
    solves: u64,
    relaxed: u64,
    braking: u64,
    rejected: u64,
    /// Longest any drone flew past its plan's end, seconds.
    overran_s: f64,
    arrived: usize,
    sim_s: f64,
}

/// tacos-sitl's body is in NED; only the vertical's sign matters to its limits.
fn ned(v: Vec3) -> Vec3 {
    Vec3::new(v.x, v.y, -v.z)
}

fn axes(v: Vec3) -> [Option<f64>; 3] {
    [Some(v.x), Some(v.y), Some(v.z)]
}

fn run(scenario: &Scenario, latency_max: f64, seed: u64) -> Result<Outcome, String> {
    let planner_cfg = PlannerConfig::from_scenario(&scenario.limits, &scenario.world);
    let motion_cfg = MotionConfig::default();
    let limits = MotionLimits::from_scenario(scenario.limits.max_speed, scenario.limits.max_accel);
    let safety = scenario.limits.safety_distance;
    let metric = Downwash::new(planner_cfg.downwash_factor);
    let mut rng = Lcg(seed.wrapping_mul(0x9E37_79B9_7F4A_7C15) ^ 0xD1B5_4A32_D192_ED03);
    let mut drones = Vec::with_capacity(N);
    let mut ids = Vec::with_capacity(N);
    for i in 0..N {
        let angle = std::f64::consts::TAU * i as f64 / N as f64;
        let altitude = 10.0 + 10.0 * ((i * 7) % N) as f64 / N as f64;
        let start = Vec3::new(RADIUS * angle.cos(), RADIUS * angle.sin(), altitude);
        let goal = Vec3::new(-start.x, -start.y, start.z);
        let id = DroneId::new(format!("d{i}")).map_err(|e| e.to_string())?;
        let mut motion = Motion::new(id.clone(), planner_cfg.clone(), motion_cfg.clone())
            .map_err(|e| e.to_string())?;
        motion.set_airborne(true);
        ids.push(id);
        drones.push(Drone {
            motion,
            body: PointMass::at_rest(ned(start)),
            goal,
            steering: Steering::Toward(Goal::fixed(goal)),
            solving: None,
            // The timers of separate processes are not in phase.
            next_solve: rng.unit() * motion_cfg.plan_period,
            arrived: false,
        });
    }
    let mut out = Outcome {
        min_pair: f64::INFINITY,
        min_clearance: f64::INFINITY,
        min_planned_scaled: f64::INFINITY,
        ..Outcome::default()
    };
    let mut reference: Vec<Reference> = drones
        .iter()
        .map(|d| Reference::hold(d.body.position))
        .collect();
    let mut step = 0usize;
    let mut now = 0.0;
    while now < MAX_SIM && drones.iter().any(|d| !d.arrived) {
        let mut published: Vec<PathMessage> = Vec::new();
        if step.is_multiple_of(CONTROL_EVERY) {
            for (i, d) in drones.iter_mut().enumerate() {
                let position = ned(d.body.position);
                let velocity = ned(d.body.velocity);
                if let Some((lands, _)) = &d.solving
                    && *lands <= now + 1e-9
                    && let Some((_, done)) = d.solving.take()
                    && let Some(path) = d.motion.solve_done(done, now)
                {
                    published.push(path);
                }
                if d.solving.is_none()
                    && now + 1e-9 >= d.next_solve
                    && let Steering::Toward(goal) = d.steering
                    && let Some(job) = d.motion.solve_job(now, position, velocity, goal, None)
                {
                    d.next_solve = now + motion_cfg.plan_period;
                    let latency = rng.unit() * latency_max;
                    d.solving = Some((now + latency, job.run()));
                } else if now + 1e-9 >= d.next_solve {
                    d.next_solve = now + motion_cfg.plan_period;
                }
                let r = d.motion.tick(now, position, velocity, d.steering).reference;
                reference[i] = Reference {
                    position: axes(ned(r.position)),
                    velocity: axes(ned(r.velocity)),
                    acceleration: axes(ned(r.acceleration)),
                };
                if (position - d.goal).norm() < ARRIVED {
                    d.arrived = true;
                }
            }
        }
        for path in published {
            for (j, d) in drones.iter_mut().enumerate() {
                if ids[j] != path.drone {
                    d.motion.on_path(path.clone());
                }
            }
        }
        for (i, d) in drones.iter_mut().enumerate() {
            d.body.track(&reference[i], &limits, PHYSICS_DT);
        }
        step += 1;
        now = step as f64 * PHYSICS_DT;
        let positions: Vec<Vec3> = drones.iter().map(|d| ned(d.body.position)).collect();
        let planned: Vec<Vec3> = reference
            .iter()
            .map(|r| {
                ned(Vec3::new(
                    r.position[0].unwrap_or(0.0),
                    r.position[1].unwrap_or(0.0),
                    r.position[2].unwrap_or(0.0),
                ))
            })
            .collect();
        for (i, p) in positions.iter().enumerate() {
            for o in &scenario.world.obstacles {
                let clearance = o.clearance_lower_bound(p);
                out.min_clearance = out.min_clearance.min(clearance);
                if clearance < scenario.limits.drone_radius {
                    out.obstacle_breach_samples += 1;
                }
            }
            for (j, q) in positions.iter().enumerate().skip(i + 1) {
                let planned_d = metric.distance(&planned[i], &planned[j]);
                out.min_planned_scaled = out.min_planned_scaled.min(planned_d);
                let d = (p - q).norm();
                out.min_pair = out.min_pair.min(d);
                if d < safety {
                    out.breach_samples += 1;
                    if out.first_breach.is_none() {
                        out.first_breach = Some(format!(
                            "t={now:.2} {} at ({:.2}, {:.2}, {:.2}) and {} at ({:.2}, {:.2}, {:.2}) {d:.2} m; planned {:.2} m apart (scaled {:.2}), tracking errors {:.2} and {:.2} m",
                            ids[i],
                            p.x,
                            p.y,
                            p.z,
                            ids[j],
                            q.x,
                            q.y,
                            q.z,
                            (planned[i] - planned[j]).norm(),
                            metric.distance(&planned[i], &planned[j]),
                            (planned[i] - p).norm(),
                            (planned[j] - q).norm(),
                        ));
                    }
                }
            }
        }
    }
    for d in &drones {
        let s = d.motion.stats();
        out.solves += s.solves;
        out.relaxed += s.relaxed;
        out.braking += s.braking;
        out.rejected += s.rejected;
        out.overran_s = out.overran_s.max(s.overran_s);
    }
    out.arrived = drones.iter().filter(|d| d.arrived).count();
    out.sim_s = now;
    Ok(out)
}

fn list(var: &str, default: &[f64]) -> Vec<f64> {
    std::env::var(var)
        .ok()
        .map(|s| {
            s.split(',')
                .filter_map(|x| x.trim().parse::<f64>().ok())
                .filter(|x| x.is_finite() && *x >= 0.0)
                .collect::<Vec<_>>()
        })
        .filter(|v| !v.is_empty())
        .unwrap_or_else(|| default.to_vec())
}

fn main() {
    let scenario = match Scenario::builtin("city") {
        Ok(s) => s,
        Err(e) => {
            eprintln!("swap loop: the city scenario: {e}");
            std::process::exit(1);
        }
    };
    let latencies = list("SWAP_LOOP_LATENCY_S", &[0.0, 0.1, 0.25, 0.45]);
    let seeds = list("SWAP_LOOP_SEEDS", &[3.0])[0].max(1.0) as u64;
    let mut failed = false;
    for latency in latencies {
        for seed in 0..seeds {
            match run(&scenario, latency, seed) {
                Ok(o) => println!(
                    "swap_loop N={N} latency_max_s={latency:.2} seed={seed} min_pair_m={:.3} min_planned_scaled_m={:.3} breach_samples={} min_clearance_m={:.3} obstacle_breach_samples={} solves={} relaxed={} braking={} rejected={} overran_s={:.2} arrived={}/{N} sim_s={:.1}{}",
                    o.min_pair,
                    o.min_planned_scaled,
                    o.breach_samples,
                    o.min_clearance,
                    o.obstacle_breach_samples,
                    o.solves,
                    o.relaxed,
                    o.braking,
                    o.rejected,
                    o.overran_s,
                    o.arrived,
                    o.sim_s,
                    o.first_breach
                        .map(|b| format!(" first_breach: {b}"))
                        .unwrap_or_default(),
                ),
                Err(e) => {
                    eprintln!("swap loop latency {latency} seed {seed}: {e}");
                    failed = true;
                }
            }
        }
    }
    if failed {
        std::process::exit(1);
    }
}
