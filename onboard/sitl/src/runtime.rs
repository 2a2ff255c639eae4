//! The I/O shell around [`Simulation`]: one UDP socket per vehicle (like PX4 SITL instance i),
//! the zenoh session, and the clocks. One task owns the simulation; per-vehicle receive
//! tasks only hand datagrams over.
//!
//! Simulated time advances at `--speed` simulated seconds per wall second, and at real time
//! while the ground says a model call is in flight (`sim/pace`). It is published on
//! `sim/clock` for the other processes of the run to follow (`--sim-clock`).

use crate::config::{ObservePx4, SitlConfig};
use crate::observed::ObservedVehicle;
use tacos_shared::frames::Home;

/// The observer's MAVLink identity on the vehicles' GCS links (a ground station's).
const GCS_SYSTEM_ID: u8 = 255;
/// MAV_COMP_ID_MISSIONPLANNER.
const GCS_COMPONENT_ID: u8 = 190;
use crate::error::SitlError;
use crate::link::{self, AUTOPILOT_COMPONENT, Handled};
use crate::sim::{Response, Simulation};
use mavlink::MavHeader;
use mavlink::dialects::common::MavMessage;
use serde::Serialize;
use std::future::Future;
use std::io::ErrorKind;
use std::net::{Ipv4Addr, SocketAddr};
use std::sync::Arc;
use std::time::Duration;
use tacos_bus::BusError;
use tacos_bus::clock::wall_unix;
use tacos_shared::messages::{FaultRequest, SimClock, SimPace};
use tokio::net::UdpSocket;
use tokio::sync::mpsc;
use tokio::task::JoinSet;
use tokio::time::{Instant, MissedTickBehavior};
use tracing::{Instrument, debug, info, info_span, warn};

/// The physics tick (wall clock).
const TICK: Duration = Duration::from_millis(10);
/// After a stall (a suspended process, a loaded machine), catch up at most this much wall time
/// at once rather than jumping the vehicles.
const MAX_CATCH_UP: f64 = 0.1;
/// The periods below are simulated seconds, as are the MAVLink stream rates (`streams`): the
/// telemetry keeps its rate in simulated time, at most one of each message per tick.
const TARGETS_PERIOD: f64 = 0.05;
const TRUTH_PERIOD: f64 = 0.1;
/// How often `sim/clock` is published (wall clock), besides at every change of rate.
const CLOCK_PERIOD: Duration = Duration::from_millis(50);
/// Large enough for several MAVLink frames in one datagram.
const DATAGRAM_BYTES: usize = 8192;

/// Runs the simulator until `shutdown` completes: binds every vehicle's UDP port, joins the
/// zenoh network, then simulates and talks. Returns an error only for set-up failures (bad
/// configuration, a port in use, zenoh not opening); trouble while running is logged.
pub async fn run(config: SitlConfig, shutdown: impl Future<Output = ()>) -> Result<(), SitlError> {
    let slots = config.validate()?.to_vec();
    let mut links = Vec::with_capacity(slots.len());
    for (i, slot) in slots.iter().enumerate() {
        if let Some(observe) = config.observe {
            links.push(observer_link(slot, i, observe).await?);
            continue;
        }
        let local = SocketAddr::from((Ipv4Addr::LOCALHOST, config.sitl_port(i)));
        let socket = UdpSocket::bind(local)
            .await
            .map_err(|error| SitlError::Bind {
                drone: slot.id.to_string(),
                addr: local,
                error,
            })?;
        links.push(VehicleLink {
            socket: Arc::new(socket),
            peer: SocketAddr::from((Ipv4Addr::LOCALHOST, config.mavlink_port(i))),
            peer_locked: false,
            local,
            system_id: u32::try_from(i + 1).unwrap_or(u32::MAX),
            component_id: AUTOPILOT_COMPONENT,
            sequence: 0,
        });
    }
    let session = config.bus.open().await?;
    let keys = config.bus.keys();
    let faults = tacos_bus::subscribe(&session, &keys.sim_faults()).await?;
    let pace = tacos_bus::subscribe_latest::<SimPace>(&session, &keys.sim_pace(), 4).await?;
    let mut sim = match config.observe {
        None => Simulation::with_px4(&config.scenario, &slots, &config.px4),
        Some(observe) => Simulation::observing(
            &config.scenario,
            slots
                .iter()
                .zip(0u8..)
                .map(|(slot, i)| {
                    ObservedVehicle::new(
                        slot.id.clone(),
                        Home::new(slot.home),
                        observe.first_sysid.saturating_add(i),
                    )
                })
                .collect(),
        ),
    };
    let mut next_gcs_heartbeat = 0.0;

    let (tx, mut rx) = mpsc::channel::<Datagram>(1024);
    let mut receivers = JoinSet::new();
    for (i, (slot, link)) in slots.iter().zip(&links).enumerate() {
        let span = info_span!("vehicle", drone = %slot.id);
        receivers.spawn(receive(i, link.socket.clone(), tx.clone()).instrument(span));
    }
    drop(tx);

    let ports: Vec<String> = slots
        .iter()
        .zip(&links)
        .map(|(s, l)| format!("{} {}→{}", s.id, l.local, l.peer.port()))
        .collect();
    info!(
        scenario = %config.scenario.name,
        swarm = %config.bus.swarm,
        speed = config.speed,
        readiness_delay_s = config.px4.readiness_delay_s,
        origin_amsl_m = config.px4.origin.amsl_m,
        link_profile = %config.px4.link_profile,
        "all {} vehicles up: {}",
        links.len(),
        ports.join(", ")
    );

    let (events_key, targets_key, truth_key) = (keys.events(), keys.targets(), keys.sim_truth());
    let mut shell = Shell {
        session: &session,
        publish_errors: 0,
    };
    let mut ticker = tokio::time::interval(TICK);
    ticker.set_missed_tick_behavior(MissedTickBehavior::Delay);
    let mut last = Instant::now();
    // Simulated time on the Unix scale starts at the wall clock, so stamps look like times.
    let epoch_unix = wall_unix() - sim.time();
    let start = sim.time();
    let mut targets = Every::new(TARGETS_PERIOD, start);
    let mut truth = Every::new(TRUTH_PERIOD, start);
    let clock_key = keys.sim_clock();
    let mut clock_published: Option<(Instant, f64)> = None;
    let mut model_call_in_flight = false;
    let mut faults_open = true;
    let mut pace_open = true;
    let mut malformed_faults = 0u64;
    let mut malformed_pace = 0u64;
    tokio::pin!(shutdown);

    loop {
        tokio::select! {
            () = &mut shutdown => break,
            Some(datagram) = rx.recv() => {
                if config.observe.is_some() {
                    for (header, message) in link::decode_datagram(&datagram.bytes).0 {
                        sim.observe(datagram.vehicle, &header, &message);
                    }
                } else if let Some(link) = links.get_mut(datagram.vehicle) {
                    on_datagram(&mut sim, link, datagram);
                }
            }
            sample = faults.recv_async(), if faults_open => match sample {
                Ok(sample) => match tacos_bus::decode::<FaultRequest>(&sample) {
                    Ok(request) => match sim.inject(&request.drone, request.fault) {
                        Some(event) => {
                            info!("{event}");
                            shell.publish_urgent(&events_key, &event).await;
                        }
                        None => warn!(drone = %request.drone, "fault request for a drone this run does not simulate"),
                    },
                    Err(e) => {
                        malformed_faults += 1;
                        warn!(count = malformed_faults, "malformed fault request ignored: {e}");
                    }
                },
                Err(e) => {
                    warn!("fault subscriber closed: {e}");
                    faults_open = false;
                }
            },
            received = pace.recv_async(), if pace_open => match received {
                Ok(Ok(p)) => {
                    if p.model_call_in_flight != model_call_in_flight {
                        debug!(model_call_in_flight = p.model_call_in_flight, "pace changed");
                    }
                    model_call_in_flight = p.model_call_in_flight;
                }
                Ok(Err(e)) => {
                    malformed_pace += 1;
                    if malformed_pace.is_power_of_two() {
                        warn!(count = malformed_pace, "malformed pace request ignored: {e}");
                    }
                }
                Err(e) => {
                    warn!("pace subscriber closed: {e}");
                    pace_open = false;
                }
            },
            _ = ticker.tick() => {
                let now = Instant::now();
                let rate = config.rate(model_call_in_flight);
                let wall_dt = now.duration_since(last).as_secs_f64().min(MAX_CATCH_UP);
                last = now;
                for event in sim.advance(wall_dt * rate) {
                    info!("{event}");
                    shell.publish_urgent(&events_key, &event).await;
                }
                let t = sim.time();
                if clock_published.is_none_or(|(at, r)| r != rate || now.duration_since(at) >= CLOCK_PERIOD) {
                    clock_published = Some((now, rate));
                    let anchor = SimClock { sim_unix_s: epoch_unix + t, wall_unix_s: wall_unix(), rate };
                    shell.publish_urgent(&clock_key, &anchor).await;
                }
                if config.observe.is_some() {
                    // A ground station's heartbeat: PX4 streams its GCS link to the first
                    // address that talks to it.
                    if t >= next_gcs_heartbeat {
                        next_gcs_heartbeat = t + 1.0;
                        for link in &mut links {
                            link.send(&crate::observed::gcs_heartbeat());
                        }
                    }
                } else {
                    for (i, link) in links.iter_mut().enumerate() {
                        for message in sim.telemetry(i) {
                            link.send(&message);
                        }
                    }
                }
                if targets.due(t) {
                    shell.publish(&targets_key, &sim.targets_message()).await;
                }
                if truth.due(t) {
                    shell.publish(&truth_key, &sim.truth()).await;
                }
            }
        }
    }

    receivers.shutdown().await;
    if let Err(e) = session.close().await {
        debug!("closing the zenoh session: {e}");
    }
    info!(sim_time = sim.time(), "simulator stopped");
    Ok(())
}

/// One datagram received on vehicle `vehicle`'s port.
struct Datagram {
    vehicle: usize,
    from: SocketAddr,
    bytes: Vec<u8>,
}

/// Forwards every datagram arriving on `socket` until the simulator goes away.
async fn receive(vehicle: usize, socket: Arc<UdpSocket>, tx: mpsc::Sender<Datagram>) {
    let mut buf = vec![0u8; DATAGRAM_BYTES];
    loop {
        match socket.recv_from(&mut buf).await {
            Ok((n, from)) => {
                let bytes = buf.get(..n).unwrap_or_default().to_vec();
                if tx
                    .send(Datagram {
                        vehicle,
                        from,
                        bytes,
                    })
                    .await
                    .is_err()
                {
                    return;
                }
            }
            // ICMP "port unreachable" from an earlier send, reported on some systems: harmless.
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::ConnectionRefused
                        | ErrorKind::ConnectionReset
                        | ErrorKind::Interrupted
                ) => {}
            Err(e) => {
                warn!("UDP receive failed, vehicle deaf from now on: {e}");
                return;
            }
        }
    }
}

/// Vehicle i's end of its MAVLink link.
struct VehicleLink {
    socket: Arc<UdpSocket>,
    /// Where everything goes, replies included: the configured remote port until a packet
    /// arrives, then the source of that first packet for good. PX4 does the same
    /// (`mavlink_receiver.cpp`: the client address is set once), so a client that comes back
    /// from another port is not heard from again.
    peer: SocketAddr,
    peer_locked: bool,
    local: SocketAddr,
    system_id: u32,
    component_id: u8,
    sequence: u8,
}

/// The observer's end of real vehicle `i`'s GCS link: an ephemeral local port talking to PX4's.
async fn observer_link(
    slot: &tacos_shared::scenario::DroneSlot,
    i: usize,
    observe: ObservePx4,
) -> Result<VehicleLink, SitlError> {
    let local = SocketAddr::from((Ipv4Addr::LOCALHOST, 0));
    let socket = UdpSocket::bind(local)
        .await
        .map_err(|error| SitlError::Bind {
            drone: slot.id.to_string(),
            addr: local,
            error,
        })?;
    let port = u16::try_from(i)
        .ok()
        .and_then(|i| observe.gcs_base_port.checked_add(i))
        .ok_or_else(|| SitlError::Config(format!("no GCS port for vehicle {i}")))?;
    Ok(VehicleLink {
        local: socket.local_addr().unwrap_or(local),
        socket: Arc::new(socket),
        peer: SocketAddr::from((Ipv4Addr::LOCALHOST, port)),
        peer_locked: true,
        system_id: u32::from(GCS_SYSTEM_ID),
        component_id: GCS_COMPONENT_ID,
        sequence: 0,
    })
}

impl VehicleLink {
    fn send(&mut self, message: &MavMessage) {
        let header = MavHeader {
            system_id: self.system_id,
            component_id: self.component_id,
            sequence: self.sequence,
        };
        self.sequence = self.sequence.wrapping_add(1);
        let bytes = link::encode(header, message);
        // UDP is lossy anyway: a full socket buffer drops the frame rather than stalling the
        // simulation.
        match self.socket.try_send_to(&bytes, self.peer) {
            Ok(_) => {}
            Err(e) if e.kind() == ErrorKind::WouldBlock => {}
            Err(e) => debug!(peer = %self.peer, "MAVLink send failed: {e}"),
        }
    }
}

fn on_datagram(sim: &mut Simulation, link: &mut VehicleLink, datagram: Datagram) {
    // A dead vehicle or a dropped link hears nothing.
    if !sim.link_up(datagram.vehicle) {
        return;
    }
    if !link.peer_locked {
        link.peer_locked = true;
        if link.peer != datagram.from {
            info!(vehicle = datagram.vehicle, partner = %datagram.from, "MAVLink partner");
        }
        link.peer = datagram.from;
    } else if datagram.from != link.peer {
        debug!(
            vehicle = datagram.vehicle,
            from = %datagram.from,
            partner = %link.peer,
            "datagram from another address: answered at the first partner, as PX4 does"
        );
    }
    let (messages, bad) = link::decode_datagram(&datagram.bytes);
    if bad > 0 {
        debug!(
            vehicle = datagram.vehicle,
            bad, "unparsable MAVLink frames skipped"
        );
    }
    for (header, message) in messages {
        let Some(Response { handled, replies }) =
            sim.handle_mavlink(datagram.vehicle, &header, &message)
        else {
            continue;
        };
        if let Handled::Command {
            command, results, ..
        } = &handled
        {
            let drone = sim
                .vehicles()
                .get(datagram.vehicle)
                .map(|v| v.id.to_string())
                .unwrap_or_default();
            info!(%drone, "{command:?} → {results:?}");
        }
        for reply in &replies {
            link.send(reply);
        }
    }
}

/// The zenoh side of the loop.
struct Shell<'a> {
    session: &'a zenoh::Session,
    publish_errors: u64,
}

impl Shell<'_> {
    async fn publish<T: Serialize>(&mut self, key: &str, value: &T) {
        let result = tacos_bus::put(self.session, key, value, tacos_bus::Delivery::Telemetry).await;
        self.check(result);
    }

    async fn publish_urgent<T: Serialize>(&mut self, key: &str, value: &T) {
        let result = tacos_bus::put(self.session, key, value, tacos_bus::Delivery::Command).await;
        self.check(result);
    }

    fn check(&mut self, result: Result<(), BusError>) {
        if let Err(e) = result {
            self.publish_errors += 1;
            // Logged at 1, 2, 4, 8 … so a broken session does not flood the log.
            if self.publish_errors.is_power_of_two() {
                warn!(count = self.publish_errors, "zenoh publish failed: {e}");
            }
        }
    }
}

/// A fixed-rate schedule on simulated time.
struct Every {
    period: f64,
    next: f64,
}

impl Every {
    fn new(period: f64, start: f64) -> Self {
        Every {
            period,
            next: start,
        }
    }

    fn due(&mut self, now: f64) -> bool {
        if now < self.next {
            return false;
        }
        self.next += self.period;
        if self.next <= now {
            self.next = now + self.period;
        }
        true
    }
}
