//! The writer's configuration: typed, validated, built by the binary from its flags.

use std::net::SocketAddr;
use std::time::Duration;
use tacos_shared::frames::Home;
use tacos_shared::{DroneId, SwarmId, Vec3};

/// Slowest accepted setpoint stream: PX4 needs > 2 Hz to enter offboard; we keep a wide margin.
pub const MIN_STREAM_RATE_HZ: f64 = 20.0;
/// Fastest accepted setpoint stream (more only loads the link).
pub const MAX_STREAM_RATE_HZ: f64 = 500.0;

/// How the writer reaches the autopilot.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum MavlinkLink {
    /// Bind this address and answer whoever sends to it (the autopilot's address is learnt from
    /// its packets), as MAVSDK's `udp://:14540` does with PX4 SITL.
    UdpIn(SocketAddr),
    /// Send to this address, from `WriterConfig::local` when given (PX4 answers only the first
    /// address that talked to it, so a writer that restarts must come back from the same port),
    /// else from an ephemeral port.
    UdpOut(SocketAddr),
    /// A serial line (a flight controller's TELEM2 port): `serial:/dev/ttyACM0:921600`.
    Serial { path: std::path::PathBuf, baud: u32 },
}

impl std::str::FromStr for MavlinkLink {
    type Err = ConfigError;

    fn from_str(raw: &str) -> Result<Self, ConfigError> {
        let bad = |why: &str| ConfigError::Link {
            raw: raw.to_owned(),
            reason: why.to_owned(),
        };
        let (scheme, addr) = raw.split_once(':').ok_or_else(|| {
            bad("expected udpin:HOST:PORT, udpout:HOST:PORT or serial:DEVICE:BAUD")
        })?;
        if scheme == "serial" {
            let (path, baud) = addr.rsplit_once(':').ok_or_else(|| {
                bad("expected serial:DEVICE:BAUD, e.g. serial:/dev/ttyACM0:921600")
            })?;
            let baud: u32 = baud
                .parse()
                .map_err(|_| bad(&format!("{baud:?} is not a baud rate")))?;
            if crate::transport::baud_constant(baud).is_none() {
                return Err(bad(&format!(
                    "unsupported baud rate {baud} (57600, 115200, 230400, 460800, 500000, 921600, 1000000, 1500000, 2000000, 3000000)"
                )));
            }
            if path.is_empty() {
                return Err(bad("the serial device is missing"));
            }
            return Ok(MavlinkLink::Serial {
                path: path.into(),
                baud,
            });
        }
        let addr: SocketAddr = addr.parse().map_err(|e| {
            bad(&format!(
                "{e} (expected an IP address and port, e.g. 127.0.0.1:14540)"
            ))
        })?;
        match scheme {
            "udpin" => Ok(MavlinkLink::UdpIn(addr)),
            "udpout" => {
                if addr.port() == 0 || addr.ip().is_unspecified() {
                    return Err(bad("udpout needs a concrete address and port to send to"));
                }
                Ok(MavlinkLink::UdpOut(addr))
            }
            other => Err(bad(&format!(
                "unknown scheme {other:?}; use udpin, udpout or serial"
            ))),
        }
    }
}

impl std::fmt::Display for MavlinkLink {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            MavlinkLink::UdpIn(a) => write!(f, "udpin:{a}"),
            MavlinkLink::UdpOut(a) => write!(f, "udpout:{a}"),
            MavlinkLink::Serial { path, baud } => write!(f, "serial:{}:{baud}", path.display()),
        }
    }
}

/// Parses a geofence given as `MINX,MINY,MINZ,MAXX,MAXY,MAXZ` (world ENU metres).
pub fn parse_geofence(raw: &str) -> Result<crate::setup::Geofence, ConfigError> {
    let bad = |why: String| ConfigError::Geofence {
        raw: raw.to_owned(),
        reason: why,
    };
    let values: Vec<f64> = raw
        .split(',')
        .map(|p| {
            p.trim()
                .parse::<f64>()
                .map_err(|e| bad(format!("{p:?}: {e}")))
        })
        .collect::<Result<_, _>>()?;
    let [x0, y0, z0, x1, y1, z1] = values[..] else {
        return Err(bad(format!("expected 6 numbers, got {}", values.len())));
    };
    if !values.iter().all(|v| v.is_finite()) || x0 >= x1 || y0 >= y1 || z0 >= z1 {
        return Err(bad(
            "each minimum must be finite and below its maximum".into()
        ));
    }
    Ok(crate::setup::Geofence {
        min: Vec3::new(x0, y0, z0),
        max: Vec3::new(x1, y1, z1),
    })
}

/// Parses `NAME=VALUE` for `--px4-param`.
pub fn parse_param(raw: &str) -> Result<crate::params::ParamWant, ConfigError> {
    let bad = |why: &str| ConfigError::Param {
        raw: raw.to_owned(),
        reason: why.to_owned(),
    };
    let (name, value) = raw
        .split_once('=')
        .ok_or_else(|| bad("expected NAME=VALUE"))?;
    let name = name.trim();
    if name.is_empty()
        || name.len() > 16
        || !name.bytes().all(|b| b.is_ascii_alphanumeric() || b == b'_')
    {
        return Err(bad("a PX4 parameter name is 1 to 16 letters, digits or _"));
    }
    let value: f64 = value
        .trim()
        .parse()
        .map_err(|_| bad("the value is not a number"))?;
    if !value.is_finite() {
        return Err(bad("the value is not finite"));
    }
    Ok(crate::params::ParamWant::set(name, value))
}

/// Parses a home given as `X,Y,Z` (world ENU metres).
pub fn parse_home(raw: &str) -> Result<Home, ConfigError> {
    let bad = |why: String| ConfigError::Home {
        raw: raw.to_owned(),
        reason: why,
    };
    let parts: Vec<&str> = raw.split(',').map(str::trim).collect();
    if parts.len() != 3 {
        return Err(bad(format!("expected X,Y,Z, got {} value(s)", parts.len())));
    }
    let mut xyz = [0.0; 3];
    for (slot, part) in xyz.iter_mut().zip(&parts) {
        let v: f64 = part.parse().map_err(|e| bad(format!("{part:?}: {e}")))?;
        if !v.is_finite() {
            return Err(bad(format!("{part:?} is not finite")));
        }
        *slot = v;
    }
    Ok(Home::new(Vec3::from(xyz)))
}

#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ConfigError {
    #[error("bad --mavlink {raw:?}: {reason}")]
    Link { raw: String, reason: String },
    #[error("bad --home {raw:?}: {reason}")]
    Home { raw: String, reason: String },
    #[error("bad --geofence {raw:?}: {reason}")]
    Geofence { raw: String, reason: String },
    #[error("bad --px4-param {raw:?}: {reason}")]
    Param { raw: String, reason: String },
    #[error("--stream-rate-hz {0} is outside [{MIN_STREAM_RATE_HZ}, {MAX_STREAM_RATE_HZ}]")]
    StreamRate(f64),
    #[error("--onboard-timeout-ms must be at least 1")]
    OnboardTimeout,
    #[error("--sysid {0} must be 1..=255")]
    SysId(u32),
    #[error("--autopilot-sysid {0} must be 1..=255")]
    AutopilotSysId(u32),
    #[error("--mavlink-local is only for udpout links (udpin binds its own address)")]
    LocalWithUdpIn,
}

fn sysid(raw: u32) -> Option<u8> {
    u8::try_from(raw).ok().filter(|s| *s != 0)
}

/// Everything one writer needs.
#[derive(Debug, Clone)]
pub struct WriterConfig {
    pub swarm: SwarmId,
    pub drone: DroneId,
    /// The vehicle's NED origin in world ENU.
    pub home: Home,
    pub link: MavlinkLink,
    /// The local address a `udpout` link sends from.
    pub local: Option<SocketAddr>,
    /// The autopilot's MAVLink system id: only its heartbeats and messages are taken.
    pub autopilot_sysid: u8,
    /// SET_POSITION_TARGET_LOCAL_NED rate.
    pub stream_rate_hz: f64,
    /// No setpoint from the planner for this long → stream a hold.
    pub onboard_timeout: Duration,
    /// No setpoint for this long while the vehicle flies → land it (see `orphan`).
    pub onboard_land_after: Duration,
    /// The scenario's box, uploaded as PX4's geofence; `None`: no fence.
    pub geofence: Option<crate::setup::Geofence>,
    /// The autopilot parameters read and set at connect.
    pub params: Vec<crate::params::ParamWant>,
    /// Parameters and fence are set and confirmed before any arming (off only for an
    /// autopilot configured by hand that lacks the parameter or mission protocol).
    pub autopilot_setup: bool,
    /// Our MAVLink system id. By default the autopilot's: PX4 tracks an onboard computer's
    /// heartbeat only from its own system (MAVSDK's companion convention), with our component
    /// 191 (MAV_COMP_ID_ONBOARD_COMPUTER).
    pub sysid: u8,
}

/// How long a vehicle is held for a silent planner before the writer lands it: room for an
/// onboard restarted by its service manager (a few seconds), short of the ground-silence
/// failsafe's 30 s landing.
pub const DEFAULT_ONBOARD_LAND_AFTER: Duration = Duration::from_secs(15);

/// The writer's MAVLink identity and peer, as given on the command line.
#[derive(Debug, Clone)]
pub struct MavlinkIds {
    pub link: MavlinkLink,
    pub local: Option<SocketAddr>,
    pub autopilot_sysid: u32,
    /// `None`: the autopilot's.
    pub sysid: Option<u32>,
}

impl WriterConfig {
    /// Checks the numbers; the ids and addresses were checked when parsed.
    pub fn new(
        swarm: SwarmId,
        drone: DroneId,
        home: Home,
        ids: MavlinkIds,
        stream_rate_hz: f64,
        onboard_timeout_ms: u64,
    ) -> Result<Self, ConfigError> {
        if !(MIN_STREAM_RATE_HZ..=MAX_STREAM_RATE_HZ).contains(&stream_rate_hz) {
            return Err(ConfigError::StreamRate(stream_rate_hz));
        }
        if onboard_timeout_ms == 0 {
            return Err(ConfigError::OnboardTimeout);
        }
        let autopilot_sysid =
            sysid(ids.autopilot_sysid).ok_or(ConfigError::AutopilotSysId(ids.autopilot_sysid))?;
        let ours = match ids.sysid {
            Some(raw) => sysid(raw).ok_or(ConfigError::SysId(raw))?,
            None => autopilot_sysid,
        };
        if ids.local.is_some() && !matches!(ids.link, MavlinkLink::UdpOut(_)) {
            return Err(ConfigError::LocalWithUdpIn);
        }
        Ok(WriterConfig {
            swarm,
            drone,
            home,
            link: ids.link,
            local: ids.local,
            autopilot_sysid,
            stream_rate_hz,
            onboard_timeout: Duration::from_millis(onboard_timeout_ms),
            onboard_land_after: DEFAULT_ONBOARD_LAND_AFTER,
            geofence: None,
            params: crate::params::failsafe_defaults(),
            autopilot_setup: true,
            sysid: ours,
        })
    }

    pub fn stream_period(&self) -> Duration {
        Duration::from_secs_f64(1.0 / self.stream_rate_hz)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn links_parse() {
        assert_eq!(
            "udpin:127.0.0.1:14540".parse::<MavlinkLink>(),
            Ok(MavlinkLink::UdpIn(SocketAddr::from((
                [127, 0, 0, 1],
                14540
            ))))
        );
        assert_eq!(
            "udpin:0.0.0.0:14540"
                .parse::<MavlinkLink>()
                .map(|l| l.to_string()),
            Ok("udpin:0.0.0.0:14540".to_owned())
        );
        assert!(matches!(
            "udpout:10.0.0.2:14580".parse::<MavlinkLink>(),
            Ok(MavlinkLink::UdpOut(_))
        ));
        for bad in [
            "",
            "udp:127.0.0.1:1",
            "udpin:localhost:14540",
            "udpin:127.0.0.1",
            "udpout:0.0.0.0:14540",
            "udpout:127.0.0.1:0",
            "serial:/dev/ttyS0",
            "serial:/dev/ttyS0:12345",
            "serial::921600",
        ] {
            assert!(bad.parse::<MavlinkLink>().is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn geofences_and_params_parse() {
        let g = parse_geofence("-10,-20,0,10,20,60");
        assert_eq!(
            g.map(|g| (g.min, g.max)),
            Ok((Vec3::new(-10.0, -20.0, 0.0), Vec3::new(10.0, 20.0, 60.0)))
        );
        for bad in [
            "",
            "1,2,3,4,5",
            "0,0,0,0,1,1",
            "0,0,0,1,1,NaN",
            "a,0,0,1,1,1",
        ] {
            assert!(parse_geofence(bad).is_err(), "{bad:?} was accepted");
        }
        assert_eq!(
            parse_param("COM_OBL_RC_ACT=4"),
            Ok(crate::params::ParamWant::set("COM_OBL_RC_ACT", 4.0))
        );
        for bad in [
            "COM_OBL_RC_ACT",
            "=1",
            "A B=1",
            "X=y",
            "WAY_TOO_LONG_PARAM_NAME=1",
            "X=inf",
        ] {
            assert!(parse_param(bad).is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn serial_links_parse() {
        assert_eq!(
            "serial:/dev/ttyACM0:921600".parse::<MavlinkLink>(),
            Ok(MavlinkLink::Serial {
                path: "/dev/ttyACM0".into(),
                baud: 921_600
            })
        );
        assert_eq!(
            "serial:/dev/ttyACM0:921600"
                .parse::<MavlinkLink>()
                .map(|l| l.to_string()),
            Ok("serial:/dev/ttyACM0:921600".to_owned())
        );
    }

    #[test]
    fn homes_parse() {
        assert_eq!(
            parse_home("10,-20.5, 3").map(|h| h.enu),
            Ok(Vec3::new(10.0, -20.5, 3.0))
        );
        for bad in ["", "1,2", "1,2,3,4", "1,x,3", "1,NaN,3", "1,inf,3"] {
            assert!(parse_home(bad).is_err(), "{bad:?} was accepted");
        }
    }

    #[test]
    fn numbers_are_checked() {
        let with = |rate, timeout, sysid: Option<u32>, autopilot_sysid, local| {
            WriterConfig::new(
                SwarmId::new("s").map_err(|_| ConfigError::OnboardTimeout)?,
                DroneId::new("alfa").map_err(|_| ConfigError::OnboardTimeout)?,
                Home::new(Vec3::zeros()),
                MavlinkIds {
                    link: MavlinkLink::UdpIn(SocketAddr::from(([127, 0, 0, 1], 14540))),
                    local,
                    autopilot_sysid,
                    sysid,
                },
                rate,
                timeout,
            )
        };
        let ok = |rate, timeout, sysid| with(rate, timeout, Some(sysid), 1, None);
        assert_eq!(
            with(50.0, 500, None, 3, None).map(|c| (c.sysid, c.autopilot_sysid)),
            Ok((3, 3)),
            "ours defaults to the autopilot's"
        );
        assert_eq!(
            with(50.0, 500, None, 0, None).err(),
            Some(ConfigError::AutopilotSysId(0))
        );
        assert_eq!(
            with(
                50.0,
                500,
                None,
                1,
                Some(SocketAddr::from(([127, 0, 0, 1], 1)))
            )
            .err(),
            Some(ConfigError::LocalWithUdpIn)
        );
        assert!(ok(50.0, 500, 245).is_ok());
        assert_eq!(
            ok(10.0, 500, 245).err(),
            Some(ConfigError::StreamRate(10.0))
        );
        assert_eq!(
            ok(f64::NAN, 500, 245)
                .err()
                .map(|e| matches!(e, ConfigError::StreamRate(_))),
            Some(true)
        );
        assert_eq!(ok(50.0, 0, 245).err(), Some(ConfigError::OnboardTimeout));
        assert_eq!(ok(50.0, 500, 0).err(), Some(ConfigError::SysId(0)));
        assert_eq!(ok(50.0, 500, 256).err(), Some(ConfigError::SysId(256)));
    }
}
