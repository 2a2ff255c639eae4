//! The receive thread: decodes every datagram from the autopilot, keeps to the configured
//! autopilot, tracks the vehicle, queues acks, texts and setup replies for the stream thread,
//! and publishes the vehicle state (on every LOCAL_POSITION_NED, on link changes, and at least
//! every 200 ms).

use super::{Ctx, FENCE, LOG_INTERVAL};
use crate::Px4Error;
use crate::config::MavlinkLink;
use crate::mav::{self, Datagram};
use crate::ratelimit::RateLimit;
use crate::setup::SetupMessage;
use crate::transport::{FrameSplitter, Peer};
use crate::vehicle::{HeartbeatVerdict, LinkChange};
use mavlink::dialects::common::{MavAutopilot, MavMessage, MavSeverity};
use std::sync::atomic::Ordering;
use std::time::{Duration, Instant};
use tacos_shared::Vec3;
use tracing::{debug, info, warn};

/// The receive thread's socket timeout: how quickly it notices shutdown and link loss.
pub(super) const RECV_TIMEOUT: Duration = Duration::from_millis(50);
/// Vehicle state is published at least this often, position or not.
const STATE_PERIOD: Duration = Duration::from_millis(200);

pub(super) fn receive_loop(ctx: &Ctx<'_>) -> Result<(), Px4Error> {
    // Larger than any datagram a MAVLink endpoint sends (several frames of ≤ 280 bytes).
    let mut buf = vec![0u8; 65_536];
    let mut last_state = Instant::now();
    let mut malformed_log = RateLimit::new(LOG_INTERVAL);
    let mut ipc_log = RateLimit::new(LOG_INTERVAL);
    // One limiter for each kind of stranger, so one cannot silence the other's warning.
    let mut foreign_log = [
        RateLimit::new(Duration::from_secs(60)),
        RateLimit::new(Duration::from_secs(60)),
    ];
    // A serial line is a byte stream: frames are cut out of it before decoding.
    let mut splitter = ctx.transport.is_stream().then(FrameSplitter::default);
    while !ctx.stopping() {
        let received = ctx.transport.recv(&mut buf).map_err(Px4Error::Socket)?;
        let now = Instant::now();
        let mut publish = false;
        // A datagram is decoded where it lies; a stream's frames once they are whole.
        let frames;
        let received: Option<(&[u8], Peer)> = match (received, splitter.as_mut()) {
            (Some((n, from)), Some(splitter)) => {
                frames = splitter.push(buf.get(..n).unwrap_or_default());
                (!frames.is_empty()).then_some((frames.as_slice(), from))
            }
            (Some((n, from)), None) => Some((buf.get(..n).unwrap_or_default(), from)),
            (None, _) => None,
        };
        if let Some((bytes, from)) = received {
            let n = bytes.len();
            ctx.datagrams.fetch_add(1, Ordering::Relaxed);
            let datagram = mav::decode_datagram(bytes);
            if datagram.is_malformed() {
                let total = ctx.malformed.fetch_add(1, Ordering::Relaxed) + 1;
                if let Some(skipped) = malformed_log.allow(now) {
                    warn!(%from, bytes = n, parse_errors = datagram.parse_errors, total, skipped, "malformed MAVLink datagram");
                }
            }
            publish = handle_datagram(ctx, datagram, from, now, &mut foreign_log);
        }
        let sample = {
            let mut shared = ctx.shared();
            match shared.vehicle.update_link(now) {
                Some(LinkChange::Up) => {
                    info!(autopilot = ?shared.vehicle.autopilot(), peer = ?shared.peer, "autopilot link up");
                    shared.link_came_up = true;
                    publish = true;
                }
                Some(LinkChange::Lost) => {
                    warn!("autopilot link lost: no heartbeat for 3 s");
                    publish = true;
                }
                None => {}
            }
            (publish || now.saturating_duration_since(last_state) >= STATE_PERIOD)
                .then(|| shared.vehicle.sample(now))
        };
        if let Some(sample) = sample {
            last_state = now;
            match ctx.ports.publish_state(sample) {
                Ok(()) => {
                    ctx.states.fetch_add(1, Ordering::Relaxed);
                }
                Err(e) => {
                    if let Some(skipped) = ipc_log.allow(now) {
                        warn!(error = %e, skipped, "cannot publish the vehicle state");
                    }
                }
            }
        }
    }
    Ok(())
}

/// Applies one datagram to the shared state; true when a new position arrived. Only messages
/// of the configured autopilot count; for `udpin` its address is learnt from its first
/// heartbeat and kept: a heartbeat of the same system id from elsewhere is taken only after the
/// link was lost (a restarted autopilot), never while the link is up.
fn handle_datagram(
    ctx: &Ctx<'_>,
    datagram: Datagram,
    from: Peer,
    now: Instant,
    foreign_log: &mut [RateLimit; 2],
) -> bool {
    let mut position = false;
    let mut shared = ctx.shared();
    let udpin = matches!(ctx.config.link, MavlinkLink::UdpIn(_));
    for (header, msg) in datagram.messages {
        let Ok(sysid) = u8::try_from(header.system_id) else {
            continue;
        };
        let compid = header.component_id;
        let from_peer = shared.peer.is_none_or(|p| p == from);
        match msg {
            MavMessage::HEARTBEAT(hb) => {
                if hb.autopilot == MavAutopilot::MAV_AUTOPILOT_INVALID {
                    continue; // a GCS or another companion computer
                }
                let relearn = udpin && !from_peer && !shared.vehicle.link_ok(now);
                if !from_peer && !relearn {
                    if let Some(skipped) = foreign_log[0].allow(now) {
                        warn!(%from, sysid, skipped, "ignoring an autopilot heartbeat from another address while the link is up");
                    }
                    continue;
                }
                match shared.vehicle.on_heartbeat(
                    now,
                    sysid,
                    compid,
                    hb.base_mode.bits(),
                    hb.custom_mode,
                    hb.system_status as u8,
                ) {
                    HeartbeatVerdict::Ours => {
                        if udpin && shared.peer != Some(from) {
                            info!(%from, "autopilot found: replying to its address");
                            shared.peer = Some(from);
                        }
                    }
                    HeartbeatVerdict::Foreign => {
                        if let Some(skipped) = foreign_log[1].allow(now) {
                            debug!(
                                sysid,
                                compid, skipped, "ignoring a heartbeat from another system"
                            );
                        }
                    }
                }
            }
            _ if !from_peer || !shared.vehicle.is_autopilot(sysid, compid) => {}
            MavMessage::LOCAL_POSITION_NED(p) => {
                let ned = Vec3::new(f64::from(p.x), f64::from(p.y), f64::from(p.z));
                let vel = Vec3::new(f64::from(p.vx), f64::from(p.vy), f64::from(p.vz));
                if ned.iter().chain(vel.iter()).all(|c| c.is_finite()) {
                    shared.vehicle.on_local_position(ned, vel, now);
                    position = true;
                }
            }
            MavMessage::GLOBAL_POSITION_INT(g) => {
                shared
                    .vehicle
                    .on_global_position((g.lat, g.lon), g.alt, g.hdg, now);
            }
            MavMessage::PARAM_VALUE(p) => {
                let value = crate::params::ParamValue::from_wire(p.param_value, p.param_type as u8);
                if let Some(value) = value {
                    let name = mav::param_name(&p.param_id[..]);
                    shared.setup.push(SetupMessage::ParamValue { name, value });
                }
            }
            MavMessage::MISSION_REQUEST_INT(r) if r.mission_type == FENCE => {
                shared.setup.push(SetupMessage::FenceRequest(r.seq))
            }
            MavMessage::MISSION_ACK(a) if a.mission_type == FENCE => {
                shared.setup.push(SetupMessage::FenceAck(a.mavtype as u8))
            }
            MavMessage::MISSION_COUNT(c) if c.mission_type == FENCE => {
                shared.setup.push(SetupMessage::FenceCount(c.count))
            }
            MavMessage::MISSION_ITEM_INT(i) if i.mission_type == FENCE => {
                shared.setup.push(SetupMessage::FenceItem {
                    seq: i.seq,
                    command: i.command as u16,
                    vertex: crate::fence::Vertex {
                        lat_e7: i.x,
                        lon_e7: i.y,
                    },
                })
            }
            MavMessage::EXTENDED_SYS_STATE(s) => {
                shared.vehicle.on_extended_sys_state(s.landed_state as u8)
            }
            MavMessage::STATUSTEXT(t) => {
                let text = mav::status_text(&t.text[..]);
                if (t.severity as u8) <= (MavSeverity::MAV_SEVERITY_WARNING as u8) {
                    warn!(text, "autopilot says");
                    shared.texts.push(text);
                } else {
                    info!(text, "autopilot says");
                }
            }
            // An ack addressed to someone else (a ground station on the same link) is not ours.
            MavMessage::COMMAND_ACK(ack)
                if ack.target_system == 0 || ack.target_system == ctx.config.sysid =>
            {
                shared
                    .acks
                    .push((mav::command_id(ack.command), ack.result as u8))
            }
            _ => {}
        }
    }
    position
}
