//! The shell: the MAVLink link (UDP or serial, `transport`), the iceoryx2 ports and two threads
//! around the pure parts.
//!
//! - The stream thread (the caller's) waits on the iceoryx2 wake-up with a timeout equal to the
//!   time to the next stream tick, drains setpoints and commands, runs the command machine and
//!   sends HEARTBEAT (1 Hz), SET_POSITION_TARGET_LOCAL_NED (stream rate, and at once for a new
//!   setpoint) and COMMAND_LONG.
//! - The receive thread decodes every datagram from the autopilot, tracks the vehicle, queues
//!   acks for the stream thread and publishes the vehicle state (on every LOCAL_POSITION_NED,
//!   on link changes, and at least every 200 ms).

use crate::Px4Error;
use crate::config::{MavlinkLink, WriterConfig};
use crate::convert::to_ned;
use crate::mav::{self, Encoder};
use crate::orphan::OrphanLanding;
use crate::procedure::{ProcedureEvent, Procedures};
use crate::ratelimit::RateLimit;
use crate::reference::{ReferenceKeeper, Source};
use crate::setup::{AutopilotSetup, SetupMessage, SetupRequest, SetupState};
use crate::transport::{Peer, Transport};
use crate::vehicle::VehicleTracker;
use mavlink::dialects::common::{MavMessage, MavMissionType};
use std::net::{Ipv4Addr, Ipv6Addr, SocketAddr, UdpSocket};
use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::time::{Duration, Instant};
use tacos_ipc::{IpcNode, WriterPorts};
use tacos_shared::ipc::CommandResultSample;
use tracing::{debug, info, warn};

mod receive;

use receive::{RECV_TIMEOUT, receive_loop};

const HEARTBEAT_PERIOD: Duration = Duration::from_secs(1);
const LOG_INTERVAL: Duration = Duration::from_secs(5);
const FENCE: MavMissionType = MavMissionType::MAV_MISSION_TYPE_FENCE;
/// What the writer asks the autopilot to stream when the link comes up, and how often (µs):
/// links in PX4's "normal" mode send LOCAL_POSITION_NED at 1 Hz unless asked, and the planner
/// needs far more. (message id, interval)
pub const STREAMS: [(u32, f32); 4] = [
    (32, 20_000.0),     // LOCAL_POSITION_NED, 50 Hz
    (33, 100_000.0),    // GLOBAL_POSITION_INT, 10 Hz: AMSL altitude and heading
    (245, 200_000.0),   // EXTENDED_SYS_STATE, 5 Hz: landed state
    (242, 1_000_000.0), // HOME_POSITION, 1 Hz
];

/// Counters of one run, returned when the writer stops.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct RunSummary {
    pub setpoints_sent: u64,
    pub setpoints_rejected: u64,
    pub commands_done: u64,
    pub datagrams_received: u64,
    pub datagrams_malformed: u64,
    pub states_published: u64,
}

/// What both threads share.
struct Shared {
    vehicle: VehicleTracker,
    /// Where the autopilot is (udpin: learnt from its packets).
    peer: Option<Peer>,
    /// (MAV_CMD, MAV_RESULT) of COMMAND_ACKs not yet seen by the stream thread.
    acks: Vec<(u32, u8)>,
    /// Warning-or-worse STATUSTEXTs not yet seen by the stream thread.
    texts: Vec<String>,
    /// The link came up and the stream thread has not yet asked for the streams and started
    /// the autopilot's setup.
    link_came_up: bool,
    /// Parameter and fence messages for the stream thread's setup.
    setup: Vec<SetupMessage>,
}

/// What the stream thread takes from the receive thread in one pass under the lock.
struct Inbox {
    acks: Vec<(u32, u8)>,
    texts: Vec<String>,
    setup_messages: Vec<SetupMessage>,
    geo_fix: Option<crate::setup::GeoFix>,
    link_came_up: bool,
    facts: crate::procedure::AutopilotFacts,
    /// The autopilot's (system, component), once known.
    target: Option<(u8, u8)>,
    view: Option<crate::reference::VehicleView>,
    peer: Option<Peer>,
    heading: Option<f64>,
}

impl Shared {
    fn take_inbox(&mut self, now: Instant) -> Inbox {
        Inbox {
            acks: std::mem::take(&mut self.acks),
            texts: std::mem::take(&mut self.texts),
            setup_messages: std::mem::take(&mut self.setup),
            geo_fix: self.vehicle.geo_fix(),
            link_came_up: std::mem::take(&mut self.link_came_up),
            facts: self.vehicle.facts(now),
            target: self.vehicle.autopilot().map(|a| (a.sysid, a.compid)),
            view: self.vehicle.view(),
            peer: self.peer,
            heading: self.vehicle.held_heading(),
        }
    }
}

struct Ctx<'a> {
    config: &'a WriterConfig,
    transport: Transport,
    ports: WriterPorts,
    shared: Mutex<Shared>,
    epoch: Instant,
    /// Set by the binary's signal handler.
    shutdown: &'a AtomicBool,
    /// Set when either thread ends, so the other one ends too.
    stop: AtomicBool,
    datagrams: AtomicU64,
    malformed: AtomicU64,
    states: AtomicU64,
}

impl Ctx<'_> {
    fn stopping(&self) -> bool {
        self.shutdown.load(Ordering::Relaxed) || self.stop.load(Ordering::Relaxed)
    }

    /// The shared state; a panic in the other thread while it held the lock leaves the data
    /// usable (every update is a plain assignment), so poisoning is ignored.
    fn shared(&self) -> std::sync::MutexGuard<'_, Shared> {
        self.shared
            .lock()
            .unwrap_or_else(|poisoned| poisoned.into_inner())
    }
}

/// Opens the link; the peer is known at once for udpout and serial, learnt for udpin.
fn open_link(
    link: &MavlinkLink,
    local: Option<SocketAddr>,
) -> Result<(Transport, Option<Peer>), Px4Error> {
    let (bind, peer) = match link {
        MavlinkLink::Serial { path, baud } => {
            return Ok((Transport::serial(path, *baud)?, Some(Peer::Line)));
        }
        MavlinkLink::UdpIn(addr) => (*addr, None),
        MavlinkLink::UdpOut(addr) => {
            let any = if addr.is_ipv4() {
                SocketAddr::from((Ipv4Addr::UNSPECIFIED, 0))
            } else {
                SocketAddr::from((Ipv6Addr::UNSPECIFIED, 0))
            };
            (local.unwrap_or(any), Some(Peer::Udp(*addr)))
        }
    };
    let socket = UdpSocket::bind(bind).map_err(|source| Px4Error::Bind { addr: bind, source })?;
    Ok((Transport::udp(socket, RECV_TIMEOUT)?, peer))
}

/// Runs one writer until `shutdown` is set (or a fatal error). Binds the socket first, so a port
/// in use fails at once.
pub fn run(config: &WriterConfig, shutdown: &AtomicBool) -> Result<RunSummary, Px4Error> {
    let (transport, peer) = open_link(&config.link, config.local)?;
    let local = transport.local();
    let node = IpcNode::new(&config.swarm, &config.drone)?;
    let ports = node.writer_ports()?;
    let epoch = Instant::now();
    info!(%local, link = %config.link, autopilot_sysid = config.autopilot_sysid, sysid = config.sysid, home = ?config.home.enu, rate_hz = config.stream_rate_hz, "MAVLink writer up");
    let ctx = Ctx {
        config,
        transport,
        ports,
        shared: Mutex::new(Shared {
            vehicle: VehicleTracker::new(config.home, epoch, config.autopilot_sysid),
            peer,
            acks: Vec::new(),
            texts: Vec::new(),
            link_came_up: false,
            setup: Vec::new(),
        }),
        epoch,
        shutdown,
        stop: AtomicBool::new(false),
        datagrams: AtomicU64::new(0),
        malformed: AtomicU64::new(0),
        states: AtomicU64::new(0),
    };
    let span = tracing::Span::current();
    let (stream_result, receive_result) = std::thread::scope(|scope| {
        let receiver = scope.spawn(|| {
            let _guard = span.enter();
            let r = receive_loop(&ctx);
            ctx.stop.store(true, Ordering::Relaxed);
            r
        });
        let s = stream_loop(&ctx);
        ctx.stop.store(true, Ordering::Relaxed);
        let r = receiver.join().unwrap_or(Err(Px4Error::ThreadPanicked));
        (s, r)
    });
    let mut summary = stream_result?;
    receive_result?;
    summary.datagrams_received = ctx.datagrams.load(Ordering::Relaxed);
    summary.datagrams_malformed = ctx.malformed.load(Ordering::Relaxed);
    summary.states_published = ctx.states.load(Ordering::Relaxed);
    let shared = ctx.shared();
    if shared.vehicle.mode() == tacos_shared::px4_mode::Px4Mode::Offboard
        && shared.vehicle.link_ok(Instant::now())
    {
        warn!("stopping while the vehicle is in OFFBOARD: PX4 will run its offboard-loss failsafe");
    }
    Ok(summary)
}

// ---- stream thread -------------------------------------------------------------------------

struct Stream<'a> {
    ctx: &'a Ctx<'a>,
    encoder: Encoder,
    keeper: ReferenceKeeper,
    orphan: OrphanLanding,
    procedures: Procedures,
    /// None until the autopilot's link first comes up (nothing to set up, or to report, before).
    setup: Option<AutopilotSetup>,
    setup_reported: SetupState,
    summary: RunSummary,
    last_source: Option<Source>,
    send_log: RateLimit,
    ipc_log: RateLimit,
    reject_log: RateLimit,
}

impl Stream<'_> {
    fn send(&mut self, peer: Peer, msg: &MavMessage, now: Instant) -> bool {
        let bytes = self.encoder.encode(msg);
        if bytes.is_empty() {
            return false;
        }
        match self.ctx.transport.send(&bytes, peer) {
            Ok(()) => true,
            Err(e) => {
                if let Some(skipped) = self.send_log.allow(now) {
                    warn!(%peer, error = %e, skipped, "MAVLink send failed");
                }
                false
            }
        }
    }

    fn setup_state(&self) -> SetupState {
        self.setup
            .as_ref()
            .map_or(SetupState::Pending, AutopilotSetup::state)
    }

    /// Logs each change of the setup's state (the parameters' values once done).
    fn report_setup(&mut self) {
        let state = self.setup_state();
        if state == self.setup_reported {
            return;
        }
        match &state {
            SetupState::Done => {
                for (name, before, after) in self.setup.iter().flat_map(AutopilotSetup::report) {
                    info!(name, before = ?before.map(|v| v.to_string()), after = ?after.map(|v| v.to_string()), "autopilot parameter");
                }
                info!(geofence = ?self.ctx.config.geofence, "autopilot set up: failsafe parameters and geofence confirmed");
            }
            SetupState::Failed(why) => {
                warn!(why, "the autopilot could not be set up: arming is refused")
            }
            SetupState::Skipped => warn!(
                "autopilot setup skipped (--no-autopilot-setup): its failsafes are as configured by hand"
            ),
            SetupState::Pending => {}
        }
        self.setup_reported = state;
    }

    fn publish_result(&mut self, result: CommandResultSample, now: Instant) {
        self.summary.commands_done += 1;
        info!(seq = result.seq, kind = result.kind, outcome = ?result.outcome(), mav_result = result.mav_result, reason = result.reason().unwrap_or(""), "command done");
        if let Err(e) = self.ctx.ports.publish_result(result)
            && let Some(skipped) = self.ipc_log.allow(now)
        {
            warn!(error = %e, skipped, "cannot publish a command result");
        }
    }

    /// Takes setpoints and commands from the planner; true when a new setpoint was accepted.
    fn drain_ipc(&mut self, now: Instant) -> bool {
        let mut fresh = false;
        match self.ctx.ports.setpoints.drain() {
            Ok(samples) => {
                for sp in samples {
                    match self.keeper.offer(&sp, now) {
                        Ok(()) => fresh = true,
                        Err(e) => {
                            if let Some(skipped) = self.reject_log.allow(now) {
                                warn!(error = %e, total = self.keeper.rejected(), skipped, "setpoint rejected");
                            }
                        }
                    }
                }
            }
            Err(e) => {
                if let Some(skipped) = self.ipc_log.allow(now) {
                    warn!(error = %e, skipped, "cannot receive setpoints");
                }
            }
        }
        match self.ctx.ports.commands.drain() {
            Ok(commands) => {
                for cmd in commands {
                    info!(
                        seq = cmd.seq,
                        kind = cmd.kind,
                        param = cmd.param,
                        "command received"
                    );
                    if let Some(result) = self.procedures.submit(cmd) {
                        self.publish_result(result, now);
                    }
                }
            }
            Err(e) => {
                if let Some(skipped) = self.ipc_log.allow(now) {
                    warn!(error = %e, skipped, "cannot receive commands");
                }
            }
        }
        fresh
    }

    fn stream_setpoint(
        &mut self,
        now: Instant,
        peer: Option<Peer>,
        target: Option<(u8, u8)>,
        view: Option<crate::reference::VehicleView>,
        held_heading: Option<f64>,
    ) {
        let Some(reference) = self.keeper.current(now, view) else {
            return;
        };
        if self.last_source != Some(reference.source) {
            match reference.source {
                Source::Planner => info!("streaming the planner's setpoints"),
                Source::HoldLastSetpoint => warn!(
                    position = ?reference.reference.position,
                    timeout_ms = self.ctx.config.onboard_timeout.as_millis(),
                    "planner silent: streaming a hold at its last setpoint"
                ),
                Source::HoldVehicle => {
                    info!(position = ?reference.reference.position, "no setpoint yet: streaming a hold at the vehicle's position")
                }
            }
            self.last_source = Some(reference.source);
        }
        let (Some(peer), Some((sysid, compid))) = (peer, target) else {
            return;
        };
        let mut ned = to_ned(&self.ctx.config.home, &reference.reference);
        // No heading from the planner: hold PX4's own instead of letting it drift (NaN yaw).
        ned.yaw = ned.yaw.or(held_heading);
        let boot_ms = now.saturating_duration_since(self.ctx.epoch).as_millis() as u32; // wraps after 49 days, as PX4's does
        let msg = mav::set_position_target(&ned, boot_ms, sysid, compid);
        if self.send(peer, &msg, now) {
            self.summary.setpoints_sent += 1;
        }
    }
}

fn stream_loop(ctx: &Ctx<'_>) -> Result<RunSummary, Px4Error> {
    let period = ctx.config.stream_period();
    let mut s = Stream {
        ctx,
        encoder: Encoder::new(ctx.config.sysid),
        keeper: ReferenceKeeper::new(ctx.config.onboard_timeout),
        orphan: OrphanLanding::new(ctx.config.onboard_land_after),
        procedures: Procedures::new(),
        setup: None,
        setup_reported: SetupState::Pending,
        summary: RunSummary::default(),
        last_source: None,
        send_log: RateLimit::new(LOG_INTERVAL),
        ipc_log: RateLimit::new(LOG_INTERVAL),
        reject_log: RateLimit::new(LOG_INTERVAL),
    };
    let start = Instant::now();
    let mut next_tick = start;
    let mut next_heartbeat = start;
    while !ctx.stopping() {
        let now = Instant::now();
        let fresh = s.drain_ipc(now);

        let Inbox {
            acks,
            texts,
            setup_messages,
            geo_fix,
            link_came_up,
            mut facts,
            target,
            view,
            peer,
            heading,
        } = ctx.shared().take_inbox(now);
        facts.link_ok = facts.link_ok && peer.is_some() && target.is_some();
        if link_came_up {
            for (message, interval_us) in STREAMS {
                s.procedures.request_stream(message, interval_us);
            }
            // A new link (first contact, or an autopilot that rebooted): set it up anew.
            s.setup = Some(if ctx.config.autopilot_setup {
                AutopilotSetup::new(
                    ctx.config.params.clone(),
                    ctx.config.geofence,
                    ctx.config.home.enu.z,
                )
            } else {
                AutopilotSetup::skipped()
            });
        }
        let mut setup_out: Vec<SetupRequest> = Vec::new();
        if let Some(setup) = s.setup.as_mut() {
            for message in setup_messages {
                setup_out.extend(setup.on_message(message, now));
            }
            setup_out.extend(setup.poll(now, geo_fix));
        }
        for text in texts {
            s.procedures.on_status_text(&text, now);
        }
        if let (Some(peer), Some((sysid, compid))) = (peer, target) {
            for request in &setup_out {
                debug!(?request, "autopilot setup");
                let msg = mav::setup_message(request, sysid, compid);
                s.send(peer, &msg, now);
            }
        }
        s.report_setup();
        s.procedures.on_setup(s.setup_state());
        let mut events = Vec::new();
        for (command, result) in acks {
            let Ok(command) = u16::try_from(command) else {
                continue;
            };
            events.extend(s.procedures.on_ack(command, result, now, &facts));
        }
        let flying =
            facts.link_ok && facts.armed && facts.mode != tacos_shared::px4_mode::Px4Mode::Land;
        if s.orphan.poll(s.keeper.last_setpoint_at(), flying, now) {
            warn!(
                after_s = s.orphan.land_after().as_secs_f64(),
                "planner silent while flying: landing the vehicle"
            );
            s.procedures.land_on_own();
        }
        events.extend(s.procedures.poll(now, &facts));
        for event in events {
            match event {
                ProcedureEvent::Done(result) => s.publish_result(result, now),
                ProcedureEvent::Internal { command, outcome } => {
                    debug!(command, ?outcome, "writer's own command done");
                }
                ProcedureEvent::Send(cmd) => {
                    let (Some(peer), Some((sysid, compid))) = (peer, target) else {
                        continue;
                    };
                    debug!(
                        command = cmd.command,
                        confirmation = cmd.confirmation,
                        "COMMAND_LONG"
                    );
                    if let Some(msg) = mav::command_long(&cmd, sysid, compid) {
                        s.send(peer, &msg, now);
                    }
                }
            }
        }

        if now >= next_heartbeat {
            if let Some(peer) = peer {
                s.send(peer, &mav::heartbeat(), now);
            }
            next_heartbeat += HEARTBEAT_PERIOD;
            if next_heartbeat <= now {
                next_heartbeat = now + HEARTBEAT_PERIOD;
            }
        }

        if fresh || now >= next_tick {
            s.stream_setpoint(now, peer, target, view, heading);
            // A new setpoint restarts the period; a late tick does not cause a burst.
            next_tick = if fresh {
                now + period
            } else {
                next_tick + period
            };
            if next_tick <= now {
                next_tick = now + period;
            }
        }

        let mut deadline = next_tick.min(next_heartbeat);
        if let Some(d) = s.procedures.next_deadline() {
            deadline = deadline.min(d);
        }
        if let Some(d) = s.setup.as_ref().and_then(AutopilotSetup::next_deadline) {
            deadline = deadline.min(d);
        }
        let timeout = deadline.saturating_duration_since(Instant::now());
        if let Err(e) = ctx.ports.wait_for_wakeup(timeout) {
            // Without the event the stream must still keep its rate: pace on the clock instead.
            if let Some(skipped) = s.ipc_log.allow(now) {
                warn!(error = %e, skipped, "iceoryx2 wake-up failed; pacing on the clock");
            }
            std::thread::sleep(timeout);
        }
    }
    s.summary.setpoints_rejected = s.keeper.rejected();
    Ok(s.summary)
}
