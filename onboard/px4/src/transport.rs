//! How the writer's bytes reach the autopilot: a UDP socket (PX4 SITL, mavlink-router, a
//! companion computer's network bridge) or a serial line (a flight controller's TELEM2 on the
//! companion computer, `serial:/dev/ttyACM0:921600`). Both read with a short timeout, so the
//! receive thread notices shutdown and link loss. A serial line carries a byte stream, not
//! datagrams: [`FrameSplitter`] (pure) cuts it into whole MAVLink frames.

use crate::Px4Error;
use std::fs::File;
use std::io::{ErrorKind, Read, Write};
use std::net::{SocketAddr, UdpSocket};
use std::os::fd::AsRawFd;
use std::path::Path;
use std::time::Duration;

/// Who a datagram came from, or where one goes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Peer {
    Udp(SocketAddr),
    /// The other end of the serial line.
    Line,
}

impl std::fmt::Display for Peer {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Peer::Udp(a) => write!(f, "{a}"),
            Peer::Line => f.write_str("the serial line"),
        }
    }
}

pub enum Transport {
    Udp(UdpSocket),
    /// The line, opened for reading and (a second handle) for writing.
    Serial {
        read: File,
        write: File,
    },
}

/// Serial speeds the writer can set (termios has no arbitrary rates).
pub fn baud_constant(baud: u32) -> Option<libc::speed_t> {
    Some(match baud {
        57_600 => libc::B57600,
        115_200 => libc::B115200,
        230_400 => libc::B230400,
        460_800 => libc::B460800,
        500_000 => libc::B500000,
        921_600 => libc::B921600,
        1_000_000 => libc::B1000000,
        1_500_000 => libc::B1500000,
        2_000_000 => libc::B2000000,
        3_000_000 => libc::B3000000,
        _ => return None,
    })
}

impl Transport {
    /// A serial line at `baud`, raw (no echo, no line discipline), reads returning after 0.1 s
    /// without data.
    pub fn serial(path: &Path, baud: u32) -> Result<Transport, Px4Error> {
        let bad = |e: std::io::Error| Px4Error::Serial {
            path: path.display().to_string(),
            source: e,
        };
        let speed = baud_constant(baud).ok_or_else(|| {
            bad(std::io::Error::new(
                ErrorKind::InvalidInput,
                format!("unsupported baud rate {baud}"),
            ))
        })?;
        let read = std::fs::OpenOptions::new()
            .read(true)
            .write(true)
            .open(path)
            .map_err(bad)?;
        let fd = read.as_raw_fd();
        // SAFETY: tcgetattr/tcsetattr on a file descriptor we own, into a zeroed termios.
        unsafe {
            let mut tio: libc::termios = std::mem::zeroed();
            if libc::tcgetattr(fd, &mut tio) != 0 {
                return Err(bad(std::io::Error::last_os_error()));
            }
            libc::cfmakeraw(&mut tio);
            tio.c_cflag |= libc::CLOCAL | libc::CREAD;
            tio.c_cc[libc::VMIN] = 0;
            tio.c_cc[libc::VTIME] = 1; // tenths of a second
            if libc::cfsetispeed(&mut tio, speed) != 0
                || libc::cfsetospeed(&mut tio, speed) != 0
                || libc::tcsetattr(fd, libc::TCSANOW, &tio) != 0
            {
                return Err(bad(std::io::Error::last_os_error()));
            }
        }
        let write = read.try_clone().map_err(bad)?;
        Ok(Transport::Serial { read, write })
    }

    pub fn udp(socket: UdpSocket, timeout: Duration) -> Result<Transport, Px4Error> {
        socket
            .set_read_timeout(Some(timeout))
            .map_err(Px4Error::Socket)?;
        Ok(Transport::Udp(socket))
    }

    /// Sends one frame (or several) to `peer`.
    pub fn send(&self, bytes: &[u8], peer: Peer) -> std::io::Result<()> {
        match (self, peer) {
            (Transport::Udp(socket), Peer::Udp(addr)) => socket.send_to(bytes, addr).map(|_| ()),
            (Transport::Serial { write, .. }, _) => (&*write).write_all(bytes),
            (Transport::Udp(_), Peer::Line) => Err(std::io::Error::new(
                ErrorKind::InvalidInput,
                "a UDP link has no serial peer",
            )),
        }
    }

    /// Reads what arrived: `None` after the timeout without data.
    pub fn recv(&self, buf: &mut [u8]) -> std::io::Result<Option<(usize, Peer)>> {
        let result = match self {
            Transport::Udp(socket) => socket.recv_from(buf).map(|(n, a)| (n, Peer::Udp(a))),
            Transport::Serial { read, .. } => (&*read).read(buf).map(|n| (n, Peer::Line)),
        };
        match result {
            Ok((0, Peer::Line)) => Ok(None),
            Ok(got) => Ok(Some(got)),
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock
                        | ErrorKind::TimedOut
                        | ErrorKind::Interrupted
                        | ErrorKind::ConnectionRefused
                        | ErrorKind::ConnectionReset
                ) =>
            {
                Ok(None)
            }
            Err(e) => Err(e),
        }
    }

    /// The local address, for the log.
    pub fn local(&self) -> String {
        match self {
            Transport::Udp(socket) => socket
                .local_addr()
                .map_or_else(|e| e.to_string(), |a| a.to_string()),
            Transport::Serial { .. } => "serial".into(),
        }
    }

    pub fn is_stream(&self) -> bool {
        matches!(self, Transport::Serial { .. })
    }
}

/// Cuts a byte stream into whole MAVLink v1/v2 frames: bytes before a start marker are dropped,
/// an incomplete frame waits for more bytes. The frames still go through the CRC-checking
/// decoder; this only finds their ends.
#[derive(Debug, Default)]
pub struct FrameSplitter {
    pending: Vec<u8>,
}

/// A runaway buffer (a line of garbage) is cut to this.
const MAX_PENDING: usize = 4096;

impl FrameSplitter {
    /// Adds `bytes`; returns the whole, CRC-valid frames found, back to back.
    pub fn push(&mut self, bytes: &[u8]) -> Vec<u8> {
        self.pending.extend_from_slice(bytes);
        let mut out = Vec::new();
        loop {
            let Some(start) = self.pending.iter().position(|b| *b == 0xFD || *b == 0xFE) else {
                self.pending.clear();
                break;
            };
            self.pending.drain(..start);
            let Some(&len) = self.pending.get(1) else {
                break;
            };
            let len = usize::from(len);
            let total = if self.pending[0] == 0xFD {
                let Some(&flags) = self.pending.get(2) else {
                    break;
                };
                let signature = if flags & 1 != 0 { 13 } else { 0 };
                10 + len + 2 + signature
            } else {
                6 + len + 2
            };
            if self.pending.len() < total {
                break;
            }
            let candidate = self.pending.get(..total).unwrap_or_default();
            if crate::mav::decode_datagram(candidate).is_malformed() {
                // A start marker inside garbage, not a frame: look again one byte later.
                self.pending.drain(..1);
                continue;
            }
            out.extend(self.pending.drain(..total));
        }
        if self.pending.len() > MAX_PENDING {
            self.pending.clear();
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mav::{Encoder, decode_datagram, heartbeat};

    #[test]
    fn a_stream_cut_anywhere_gives_back_whole_frames() {
        let mut enc = Encoder::new(1);
        let mut stream = b"noise".to_vec();
        for _ in 0..3 {
            stream.extend(enc.encode(&heartbeat()));
        }
        for cut in 1..stream.len() {
            let mut s = FrameSplitter::default();
            let mut frames = s.push(&stream[..cut]);
            frames.extend(s.push(&stream[cut..]));
            let d = decode_datagram(&frames);
            assert_eq!((d.messages.len(), d.parse_errors), (3, 0), "cut at {cut}");
        }
    }

    #[test]
    fn garbage_is_dropped_and_a_partial_frame_waits() {
        let mut s = FrameSplitter::default();
        assert!(s.push(&[0u8; 10_000]).is_empty());
        // A false start marker with a length that swallows a real frame does not lose it.
        let real = Encoder::new(1).encode(&heartbeat());
        let mut bytes = vec![0xFD, 3, 0, 0, 0];
        bytes.extend(&real);
        bytes.extend(&real);
        assert_eq!(decode_datagram(&s.push(&bytes)).messages.len(), 2);
        let frame = Encoder::new(1).encode(&heartbeat());
        assert!(s.push(&frame[..5]).is_empty(), "not whole yet");
        assert_eq!(s.push(&frame[5..]), frame);
        assert!(baud_constant(921_600).is_some() && baud_constant(12_345).is_none());
    }
}
