//! The field network across hosts: a router host, a ground host, two drone hosts and an
//! intruder host, each a network namespace with its own address on one LAN (made and removed by
//! the test), running the shipped binaries with the shipped `deploy/zenoh/` files (only the
//! certificate paths, the router's address and the swarm name changed) and certificates from
//! `deploy/certs.sh`. Each drone host runs its own simulated autopilot (`tacos-sitl` with that one
//! vehicle), `tacos-px4` and `tacos-onboard`; this test is the ground station, on the ground host.
//!
//! Shown, with figures printed as `figure:` lines:
//! - the swarm takes off and flies to points through the router over mutual TLS;
//! - hosts with another CA's certificate, or none, never join, and say so in their own log;
//! - alfa's certificate cannot put bravo's action, the heartbeat, a target or bravo's status: the
//!   router refuses and counts each, and bravo flies on;
//! - bravo's host partitioned while a mission gives it work: bravo holds within its failsafe time
//!   and lands later, the ground marks it lost and its mission replans, handing bravo's unstarted
//!   work to alfa (a stand-in model: `multi_host/mission.rs`); when the link is back bravo is
//!   seen again;
//! - the ground station restarted mid-flight: a new `tacos-ground send` waits until alfa follows
//!   it and lands it.
//!
//! Needs root and iproute2; without them it says so and passes, except under `CI=true`.

#[path = "multi_host/mission.rs"]
mod mission;

use std::path::{Path, PathBuf};
use std::sync::Arc;
use std::time::{Duration, Instant};
use tacos_bus::BusArgs;
use tacos_ground::direct::run_actions;
use tacos_ground::launch::bin_dir;
use tacos_ground::link::{GroundLink, GroundRole};
use tacos_ground::mission::MissionUpdate;
use tacos_ground::safety::SafetyGate;
use tacos_ground::swarm::SwarmChange;
use tacos_shared::action::Action;
use tacos_shared::{DroneId, DroneMode, SwarmId, Vec3};
use tacos_tests::deploy::{make_certs, repo, shipped_zenoh as shipped};
use tacos_tests::netns::{self, Hosts, Lan};
use tacos_tests::{id, unique_swarm};

const HOSTS: [&str; 5] = ["router", "ground", "alfa", "bravo", "intruder"];
const DRONES: [&str; 2] = ["alfa", "bravo"];
/// The onboard's default ground-silence failsafe: hold after 3 s, land after 30 s.
const HOLD_AFTER_S: f64 = 3.0;
const LAND_AFTER_S: f64 = 30.0;

#[test]
fn a_swarm_flies_through_the_router_across_hosts_and_keeps_intruders_partitions_and_a_ground_restart_in_hand()
-> anyhow::Result<()> {
    if let Some(why) = netns::unavailable() {
        anyhow::ensure!(
            std::env::var("CI").as_deref() != Ok("true"),
            "CI=true, but {why}"
        );
        eprintln!("skipped: {why}; run the tests as root with iproute2 installed");
        return Ok(());
    }
    let lan = Lan::create(&HOSTS)?;
    // This thread, and every thread it starts (the runtime's, zenoh's), is the ground host.
    lan.enter("ground")?;
    let runtime = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()?;
    let result = runtime.block_on(fly(&lan));
    drop(runtime);
    result
}

/// The shipped files with this run's paths, router address and swarm.
struct Configs {
    dir: PathBuf,
    certs: PathBuf,
    router_addr: String,
    swarm: SwarmId,
}

impl Configs {
    fn for_swarm(&self, text: &str) -> String {
        text.replace("tacos/default/", &format!("tacos/{}/", self.swarm))
    }

    fn router(&self) -> anyhow::Result<PathBuf> {
        let text = self
            .for_swarm(&shipped("router.json5")?)
            .replace("/etc/tacos/certs/", &format!("{}/", self.certs.display()));
        self.write("router.json5", &text)
    }

    /// `client.json5` for a principal whose certificate is `cert_dir/<name>.pem`, or for a
    /// host that shows none.
    fn client(&self, file: &str, cert: Option<(&Path, &str)>) -> anyhow::Result<PathBuf> {
        let mut text = shipped("client.json5")?
            .replace(
                "quic/tacos-router:7447",
                &format!("quic/{}:7447", self.router_addr),
            )
            .replace(
                "/etc/tacos/certs/ca.pem",
                &self.certs.join("ca.pem").display().to_string(),
            );
        match cert {
            Some((dir, name)) => {
                text = text
                    .replace(
                        "/etc/tacos/certs/self.pem",
                        &dir.join(format!("{name}.pem")).display().to_string(),
                    )
                    .replace(
                        "/etc/tacos/certs/self-key.pem",
                        &dir.join(format!("{name}-key.pem")).display().to_string(),
                    );
            }
            None => {
                text = text
                    .replace("enable_mtls: true", "enable_mtls: false")
                    .lines()
                    .filter(|l| {
                        !l.contains("connect_certificate") && !l.contains("connect_private_key")
                    })
                    .collect::<Vec<_>>()
                    .join("\n");
            }
        }
        self.write(file, &text)
    }

    fn write(&self, file: &str, text: &str) -> anyhow::Result<PathBuf> {
        let path = self.dir.join(file);
        std::fs::write(&path, text)?;
        Ok(path)
    }
}

/// The lab map with only `drone`'s slot: what that drone host's simulator flies.
fn one_vehicle_scenario(drone: &str) -> anyhow::Result<String> {
    let text = std::fs::read_to_string(repo().join("shared/scenarios/lab.toml"))?;
    let mut out = Vec::new();
    let mut block: Option<Vec<&str>> = None;
    for line in text.lines() {
        if let Some(b) = block.as_mut() {
            if line.starts_with('[') || line.starts_with('#') {
                let b = block.take().unwrap_or_default();
                if b.iter().any(|l| *l == format!("id = {drone:?}")) {
                    out.extend(b);
                }
            } else {
                b.push(line);
                continue;
            }
        }
        if line == "[[drones]]" {
            block = Some(vec![line]);
        } else {
            out.push(line);
        }
    }
    Ok(out.join("\n") + "\n")
}

fn figure(text: impl AsRef<str>) {
    println!("figure: {}", text.as_ref());
}

async fn fly(lan: &Lan) -> anyhow::Result<()> {
    let dir = std::env::temp_dir().join(format!("tacos-multi-host-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir)?;
    let certs = dir.join("certs");
    let router_addr = lan.addr("router");
    make_certs(
        &certs,
        &[&format!("router={router_addr}"), "ground", "alfa", "bravo"],
    )?;
    let other_ca = dir.join("other-ca");
    make_certs(&other_ca, &["ground"])?;
    let configs = Configs {
        dir: dir.clone(),
        certs: certs.clone(),
        router_addr,
        swarm: unique_swarm("mh"),
    };
    let swarm = configs.swarm.to_string();
    let bins = bin_dir();
    let bin = |name: &str| bins.join(name);
    let mut hosts = Hosts::new(lan, &dir);

    let router = configs.router()?;
    let started = Instant::now();
    hosts.start(
        "router",
        "router",
        &bin("tacos-router"),
        &["--zenoh-config", &router.display().to_string()],
    )?;
    for drone in DRONES {
        let scenario = configs.write(&format!("{drone}.toml"), &one_vehicle_scenario(drone)?)?;
        let client = configs.client(&format!("{drone}.json5"), Some((&certs, drone)))?;
        hosts.start(
            drone,
            &format!("sitl-{drone}"),
            &bin("tacos-sitl"),
            &[
                "--scenario",
                &scenario.display().to_string(),
                "--drones",
                "1",
            ],
        )?;
        let home = if drone == "alfa" {
            "-1,-3.5,0"
        } else {
            "0,-3.5,0"
        };
        hosts.start(
            drone,
            &format!("px4-{drone}"),
            &bin("tacos-px4"),
            &[
                "--swarm",
                &swarm,
                "--drone",
                drone,
                "--home",
                home,
                "--mavlink",
                "udpin:127.0.0.1:14540",
                "--autopilot-sysid",
                "1",
                "--geofence=-4,-4,0,4,4,2.5",
            ],
        )?;
        hosts.start(
            drone,
            &format!("onboard-{drone}"),
            &bin("tacos-onboard"),
            &[
                "--swarm",
                &swarm,
                "--drone",
                drone,
                "--scenario",
                "lab",
                "--zenoh-config",
                &client.display().to_string(),
            ],
        )?;
    }
    // Two intruders: a certificate of another CA in the ground's name, and none.
    let intruders = [
        (
            "intruder-other-ca",
            configs.client("other-ca.json5", Some((&other_ca, "ground")))?,
        ),
        ("intruder-no-cert", configs.client("no-cert.json5", None)?),
    ];
    for (name, config) in &intruders {
        hosts.start(
            "intruder",
            name,
            &bin("tacos-ground"),
            &[
                "swarm",
                "--swarm",
                &swarm,
                "--count",
                "1",
                "--zenoh-config",
                &config.display().to_string(),
            ],
        )?;
    }

    // The ground station, on its host, over mutual TLS through the router.
    let ground_config = configs.client("ground.json5", Some((&certs, "ground")))?;
    let mut bus = BusArgs::loopback(configs.swarm.clone(), None, vec![]);
    bus.config_file = Some(ground_config.clone());
    let link = Arc::new(GroundLink::connect_as(&bus, GroundRole::InControl).await?);
    let mut membership = link.membership();
    let ids: Vec<DroneId> = DRONES.iter().map(|d| id(d)).collect();
    link.wait_for_drones(&ids, Duration::from_secs(60), |s| {
        s.autopilot_link && s.mode == DroneMode::Idle
    })
    .await?;
    figure(format!(
        "both drones heard through the router, on the ground and ready, {:.1} s after the hosts started",
        started.elapsed().as_secs_f64()
    ));
    if let Some(exit) = hosts.exited() {
        anyhow::bail!("{exit}");
    }

    let scenario = tacos_bus::load_scenario("lab")?;
    let gate = SafetyGate::new(scenario.clone());
    let t = Instant::now();
    let takeoffs: Vec<_> = ids
        .iter()
        .map(|d| (d.clone(), Action::ArmTakeoff))
        .collect();
    run_actions(&link, &gate, &takeoffs, None, Duration::from_secs(60)).await?;
    let points = [Vec3::new(-1.0, -2.0, 1.0), Vec3::new(0.5, -2.0, 1.2)];
    let gotos: Vec<_> = ids
        .iter()
        .zip(points)
        .map(|(d, p)| (d.clone(), Action::Goto { target: p }))
        .collect();
    run_actions(&link, &gate, &gotos, None, Duration::from_secs(60)).await?;
    for (d, p) in ids.iter().zip(points) {
        let at = link
            .view()
            .get(d)
            .and_then(|e| e.status.as_ref())
            .map(|s| s.position)
            .ok_or_else(|| anyhow::anyhow!("{d} has no status"))?;
        anyhow::ensure!((at - p).norm() < 0.3, "{d} is at {at:?}, not at {p:?}");
    }
    figure(format!(
        "take-off and flight to points through the router: {:.1} s",
        t.elapsed().as_secs_f64()
    ));

    // The intruders have been trying since the start.
    for (name, _) in &intruders {
        hosts
            .log_says(
                name,
                "not joined the swarm network after 5 s",
                Duration::from_secs(15),
            )
            .await?;
        let log = hosts.read_log(name);
        anyhow::ensure!(
            !log.contains(&format!("swarm {swarm}")),
            "{name} joined and printed the swarm's table:\n{log}"
        );
    }
    figure("the intruders (another CA's certificate; none) never joined and said so every 5 s");

    // A compromised drone host: alfa's certificate forging what only others may put.
    let bravo_seq = link
        .view()
        .get(&ids[1])
        .and_then(|e| e.status.as_ref())
        .and_then(|s| s.action.as_ref())
        .map(|a| a.seq);
    let forged = 20;
    let forge = hosts
        .command(
            "alfa",
            "forge",
            Path::new(env!("CARGO_BIN_EXE_tacos-forge")),
        )?
        .args([
            "--zenoh-config",
            &dir.join("alfa.json5").display().to_string(),
            "--swarm",
            &swarm,
            "--victim",
            "bravo",
            "--count",
            &forged.to_string(),
        ])
        .status();
    let status = tokio::time::timeout(Duration::from_secs(40), forge).await??;
    anyhow::ensure!(
        status.success(),
        "tacos-forge failed:\n{}",
        hosts.read_log("forge")
    );
    let keys = tacos_shared::keys::Keys::new(&configs.swarm);
    let bravo = ids[1].clone();
    let forged_keys = [
        keys.action(&bravo),
        keys.ground_heartbeat(),
        keys.targets(),
        keys.status(&bravo),
    ];
    for key in &forged_keys {
        let wait = Duration::from_secs(6);
        let line = format!("key={key} total={forged}");
        hosts.log_says("router", &line, wait).await.map_err(|e| {
            anyhow::anyhow!("the router did not count {forged} refused puts on {key}: {e}")
        })?;
    }
    let router_log = hosts.read_log("router");
    anyhow::ensure!(
        router_log
            .lines()
            .filter(|l| l.contains("refused by the access control"))
            .all(|l| l.contains("principal=alfa ")),
        "refusals counted for someone other than alfa:\n{router_log}"
    );
    {
        let view = link.view();
        let s = view
            .get(&bravo)
            .and_then(|e| e.status.as_ref())
            .ok_or_else(|| anyhow::anyhow!("bravo has no status"))?;
        anyhow::ensure!(
            s.mode == DroneMode::Flying && s.action.as_ref().map(|a| a.seq) == bravo_seq,
            "bravo was affected by the forgeries: {s:?}"
        );
    }
    figure(format!(
        "{forged} forged puts on each of bravo's action, the heartbeat, the targets and bravo's status: all refused and counted by the router; bravo flew on"
    ));

    // The latency tool across the hosts: alfa's slot answered from alfa's host with alfa's
    // certificate, pinged from the ground host with the ground's, through the router.
    let alfa_config = dir.join("alfa.json5").display().to_string();
    let ground_arg = ground_config.display().to_string();
    hosts.start(
        "alfa",
        "latency-pong",
        &bin("tacos-latency"),
        &[
            "pong",
            "--swarm",
            &swarm,
            "--drone",
            "alfa",
            "--zenoh-config",
            &alfa_config,
        ],
    )?;
    let ping = hosts
        .command("ground", "latency-ping", &bin("tacos-latency"))?
        .args([
            "ping",
            "--swarm",
            &swarm,
            "--drone",
            "alfa",
            "--zenoh-config",
            &ground_arg,
            "--count",
            "300",
            "--warmup",
            "50",
        ])
        .status();
    let status = tokio::time::timeout(Duration::from_secs(90), ping).await??;
    let report = hosts.read_log("latency-ping");
    anyhow::ensure!(status.success(), "tacos-latency ping failed:\n{report}");
    for name in ["bare zenoh", "tacos ", "tacos / bare"] {
        let line = report
            .lines()
            .find(|l| l.starts_with(name))
            .ok_or_else(|| anyhow::anyhow!("no {name:?} line:\n{report}"))?;
        figure(format!(
            "latency, ground host to alfa's host through the router over QUIC: {line}"
        ));
    }

    // A mission gives bravo work; bravo's host is partitioned as soon as its first goto is sent
    // (what the ground heard of members before is not news).
    while membership.try_recv().is_ok() {}
    let mut running = mission::start(link.clone(), SafetyGate::new(scenario), &dir).await?;
    running
        .until(
            "bravo's first goto",
            Duration::from_secs(30),
            |u| matches!(u, MissionUpdate::Sent { drone, .. } if drone == "bravo"),
        )
        .await?;
    lan.set_link("bravo", false)?;
    let cut = Instant::now();
    let lost = tokio::time::timeout(Duration::from_secs(15), async {
        loop {
            match membership.recv().await {
                Ok(SwarmChange::Left(d)) if d == bravo => return Ok(cut.elapsed()),
                Ok(_) => {}
                Err(e) => return Err(anyhow::anyhow!("membership: {e}")),
            }
        }
    })
    .await
    .map_err(|_| anyhow::anyhow!("the ground never marked bravo lost"))??;
    figure(format!(
        "bravo partitioned: marked lost by the ground after {:.1} s",
        lost.as_secs_f64()
    ));
    hosts
        .log_says(
            "onboard-bravo",
            "stage=Some(Holding)",
            Duration::from_secs(10),
        )
        .await?;
    // Polled every 0.1 s: read within that of the line being written.
    let hold = cut.elapsed();
    figure(format!(
        "bravo held {:.1} s after the cut (failsafe: {HOLD_AFTER_S} s of silence)",
        hold.as_secs_f64()
    ));
    anyhow::ensure!(
        hold.as_secs_f64() < HOLD_AFTER_S + 1.5,
        "bravo held late: {hold:?}"
    );
    hosts
        .log_says(
            "onboard-bravo",
            "stage=Some(Landing)",
            Duration::from_secs(45),
        )
        .await?;
    let land = cut.elapsed();
    figure(format!(
        "bravo began landing {:.1} s after the cut (failsafe: {LAND_AFTER_S} s of silence)",
        land.as_secs_f64()
    ));
    anyhow::ensure!(
        (LAND_AFTER_S - 1.0..LAND_AFTER_S + 3.0).contains(&land.as_secs_f64()),
        "bravo began landing at {land:?}"
    );
    anyhow::ensure!(
        link.view().get(&ids[0]).is_some_and(|e| e.alive),
        "alfa was lost too"
    );
    // The mission went on without bravo: replanned, alfa took bravo's unstarted work.
    running
        .until("the replanned mission", Duration::from_secs(30), |u| {
            matches!(u, MissionUpdate::PlanComplete { .. })
        })
        .await?;
    let log_path = running.log_path.clone();
    running.stop().await?;
    let (replan_s, done_s) = mission::replanned(&log_path)?;
    figure(format!(
        "the ground's mission replanned {replan_s:.1} s after bravo's goto was sent and cut off; alfa was given bravo's unstarted goto and finished it at {done_s:.1} s"
    ));

    // The link back.
    lan.set_link("bravo", true)?;
    let back = Instant::now();
    link.wait_for_drones(
        std::slice::from_ref(&bravo),
        Duration::from_secs(30),
        |_| true,
    )
    .await?;
    figure(format!(
        "bravo's link back: seen again after {:.1} s",
        back.elapsed().as_secs_f64()
    ));
    link.wait_for_drones(std::slice::from_ref(&bravo), Duration::from_secs(30), |s| {
        s.mode == DroneMode::Idle && !s.armed
    })
    .await?;
    figure(format!(
        "bravo on the ground and disarmed {:.1} s after its link came back",
        back.elapsed().as_secs_f64()
    ));

    // The ground station restarted mid-flight: this one stops, a new `send` takes over.
    drop(membership);
    drop(link);
    let restart = Instant::now();
    let send = hosts
        .command("ground", "send", &bin("tacos-ground"))?
        .args([
            "send",
            "--swarm",
            &swarm,
            "--zenoh-config",
            &ground_config.display().to_string(),
            "--scenario",
            "lab",
            "alfa",
            "land",
        ])
        .status();
    let status = tokio::time::timeout(Duration::from_secs(60), send).await??;
    let out = hosts.read_log("send");
    anyhow::ensure!(status.success(), "send after the restart failed:\n{out}");
    anyhow::ensure!(out.contains("alfa: land() done"), "{out}");
    let follows = out
        .lines()
        .find_map(|l| {
            l.strip_prefix("alfa follows this ground station (")
                .and_then(|r| r.split(' ').next())
                .and_then(|s| s.parse::<f64>().ok())
        })
        .ok_or_else(|| anyhow::anyhow!("send did not say when alfa followed it:\n{out}"))?;
    figure(format!(
        "ground restarted: the new ground in control of alfa {follows:.1} s after it started, alfa landed {:.1} s after the restart",
        restart.elapsed().as_secs_f64()
    ));
    anyhow::ensure!(
        follows < HOLD_AFTER_S + 3.0,
        "the restarted ground took {follows} s to be followed"
    );
    if let Some(exit) = hosts.exited() {
        anyhow::bail!("{exit}");
    }
    Ok(())
}
