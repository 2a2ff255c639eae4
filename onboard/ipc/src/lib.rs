//! The iceoryx2 channels between `tacos-onboard` (planner side) and `tacos-px4` (MAVLink writer)
//! on one companion computer.
//!
//! Both processes open every service through the functions here, so the quality-of-service
//! settings (buffer sizes, history, port counts) always match; a mismatch would make `open` fail.
//! Ports use `ipc_threadsafe` so they can live inside async tasks.

use iceoryx2::port::listener::Listener;
use iceoryx2::port::notifier::Notifier;
use iceoryx2::port::publisher::Publisher;
use iceoryx2::port::subscriber::Subscriber;
use iceoryx2::prelude::*;
use std::time::Duration;
use tacos_shared::ipc::{CommandResultSample, CommandSample, SetpointSample, VehicleStateSample};
use tacos_shared::keys::{IpcChannel, ipc_service};
use tacos_shared::{DroneId, SwarmId};

type Svc = ipc_threadsafe::Service;

#[derive(Debug, thiserror::Error)]
pub enum IpcError {
    #[error("iceoryx2 node: {0}")]
    Node(String),
    #[error("iceoryx2 service {service}: {reason}")]
    Service { service: String, reason: String },
    #[error("iceoryx2 {port} port on {service}: {reason}")]
    Port {
        service: String,
        port: &'static str,
        reason: String,
    },
    #[error("iceoryx2 send on {service}: {reason}")]
    Send { service: String, reason: String },
    #[error("iceoryx2 receive on {service}: {reason}")]
    Receive { service: String, reason: String },
}

/// One drone's iceoryx2 node. Signal handling is left to the binary.
pub struct IpcNode {
    node: Node<Svc>,
    swarm: SwarmId,
    drone: DroneId,
}

fn service_name(name: &str) -> Result<ServiceName, IpcError> {
    ServiceName::new(name).map_err(|e| IpcError::Service {
        service: name.to_owned(),
        reason: format!("{e:?}"),
    })
}

impl IpcNode {
    pub fn new(swarm: &SwarmId, drone: &DroneId) -> Result<Self, IpcError> {
        // iceoryx2 logs to stdout at warning level (e.g. "no config file"); keep it to errors
        // unless IOX2_LOG_LEVEL says otherwise.
        set_log_level_from_env_or(LogLevel::Error);
        let node = NodeBuilder::new()
            .signal_handling_mode(SignalHandlingMode::Disabled)
            .create::<Svc>()
            .map_err(|e| IpcError::Node(format!("{e:?}")))?;
        // A previous run that was killed leaves its node behind; reclaim it so services open.
        let _ = node.try_cleanup_dead_nodes();
        Ok(IpcNode {
            node,
            swarm: swarm.clone(),
            drone: drone.clone(),
        })
    }

    fn name(&self, channel: IpcChannel) -> String {
        ipc_service(&self.swarm, &self.drone, channel)
    }

    fn pubsub<T: std::fmt::Debug + ZeroCopySend + 'static>(
        &self,
        channel: IpcChannel,
        buffer: usize,
        history: usize,
    ) -> Result<
        (
            String,
            iceoryx2::service::port_factory::publish_subscribe::PortFactory<Svc, T, ()>,
        ),
        IpcError,
    > {
        let name = self.name(channel);
        let factory = self
            .node
            .service_builder(&service_name(&name)?)
            .publish_subscribe::<T>()
            .max_publishers(2)
            .max_subscribers(4)
            .subscriber_max_buffer_size(buffer)
            .history_size(history)
            .enable_safe_overflow(true)
            .open_or_create()
            .map_err(|e| IpcError::Service {
                service: name.clone(),
                reason: format!("{e:?}"),
            })?;
        Ok((name, factory))
    }

    fn publisher<T: std::fmt::Debug + ZeroCopySend + 'static>(
        &self,
        channel: IpcChannel,
        buffer: usize,
        history: usize,
    ) -> Result<Sender<T>, IpcError> {
        let (name, factory) = self.pubsub::<T>(channel, buffer, history)?;
        let port = factory
            .publisher_builder()
            .create()
            .map_err(|e| IpcError::Port {
                service: name.clone(),
                port: "publisher",
                reason: format!("{e:?}"),
            })?;
        Ok(Sender { port, name })
    }

    fn subscriber<T: std::fmt::Debug + ZeroCopySend + Copy + 'static>(
        &self,
        channel: IpcChannel,
        buffer: usize,
        history: usize,
    ) -> Result<Receiver<T>, IpcError> {
        let (name, factory) = self.pubsub::<T>(channel, buffer, history)?;
        let port = factory
            .subscriber_builder()
            .create()
            .map_err(|e| IpcError::Port {
                service: name.clone(),
                port: "subscriber",
                reason: format!("{e:?}"),
            })?;
        Ok(Receiver { port, name })
    }

    fn event(
        &self,
    ) -> Result<
        (
            String,
            iceoryx2::service::port_factory::event::PortFactory<Svc>,
        ),
        IpcError,
    > {
        let name = self.name(IpcChannel::Wakeup);
        let factory = self
            .node
            .service_builder(&service_name(&name)?)
            .event()
            .max_notifiers(2)
            .max_listeners(2)
            .open_or_create()
            .map_err(|e| IpcError::Service {
                service: name.clone(),
                reason: format!("{e:?}"),
            })?;
        Ok((name, factory))
    }

    /// The ports of the planner side (`tacos-onboard`).
    pub fn onboard_ports(&self) -> Result<OnboardPorts, IpcError> {
        let (wake_name, events) = self.event()?;
        let wakeup = events
            .notifier_builder()
            .create()
            .map_err(|e| IpcError::Port {
                service: wake_name.clone(),
                port: "notifier",
                reason: format!("{e:?}"),
            })?;
        Ok(OnboardPorts {
            setpoints: self.publisher(IpcChannel::Setpoint, SETPOINT_BUFFER, 1)?,
            commands: self.publisher(IpcChannel::Command, COMMAND_BUFFER, 0)?,
            wakeup: Wake {
                port: wakeup,
                name: wake_name,
            },
            results: self.subscriber(IpcChannel::CommandResult, COMMAND_BUFFER, 0)?,
            state: self.subscriber(IpcChannel::VehicleState, STATE_BUFFER, 1)?,
        })
    }

    /// The ports of the MAVLink writer (`tacos-px4`).
    pub fn writer_ports(&self) -> Result<WriterPorts, IpcError> {
        let (wake_name, events) = self.event()?;
        let listener = events
            .listener_builder()
            .create()
            .map_err(|e| IpcError::Port {
                service: wake_name.clone(),
                port: "listener",
                reason: format!("{e:?}"),
            })?;
        Ok(WriterPorts {
            setpoints: self.subscriber(IpcChannel::Setpoint, SETPOINT_BUFFER, 1)?,
            commands: self.subscriber(IpcChannel::Command, COMMAND_BUFFER, 0)?,
            wakeup: listener,
            wake_name,
            results: self.publisher(IpcChannel::CommandResult, COMMAND_BUFFER, 0)?,
            state: self.publisher(IpcChannel::VehicleState, STATE_BUFFER, 1)?,
        })
    }
}

const SETPOINT_BUFFER: usize = 4;
const COMMAND_BUFFER: usize = 16;
const STATE_BUFFER: usize = 4;

/// A typed publisher.
pub struct Sender<T: std::fmt::Debug + ZeroCopySend + 'static> {
    port: Publisher<Svc, T, ()>,
    name: String,
}

impl<T: std::fmt::Debug + ZeroCopySend + 'static> Sender<T> {
    pub fn send(&self, value: T) -> Result<(), IpcError> {
        let sample = self.port.loan_uninit().map_err(|e| IpcError::Send {
            service: self.name.clone(),
            reason: format!("{e:?}"),
        })?;
        sample
            .write_payload(value)
            .send()
            .map_err(|e| IpcError::Send {
                service: self.name.clone(),
                reason: format!("{e:?}"),
            })?;
        Ok(())
    }
}

/// A typed subscriber of `Copy` payloads.
pub struct Receiver<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> {
    port: Subscriber<Svc, T, ()>,
    name: String,
}

impl<T: std::fmt::Debug + ZeroCopySend + Copy + 'static> Receiver<T> {
    /// The next sample, if one is waiting.
    pub fn try_recv(&self) -> Result<Option<T>, IpcError> {
        match self.port.receive() {
            Ok(Some(sample)) => Ok(Some(*sample)),
            Ok(None) => Ok(None),
            Err(e) => Err(IpcError::Receive {
                service: self.name.clone(),
                reason: format!("{e:?}"),
            }),
        }
    }

    /// Drains the buffer and returns the newest sample.
    pub fn latest(&self) -> Result<Option<T>, IpcError> {
        let mut last = None;
        while let Some(v) = self.try_recv()? {
            last = Some(v);
        }
        Ok(last)
    }

    /// Drains the buffer.
    pub fn drain(&self) -> Result<Vec<T>, IpcError> {
        let mut all = Vec::new();
        while let Some(v) = self.try_recv()? {
            all.push(v);
        }
        Ok(all)
    }
}

struct Wake {
    port: Notifier<Svc>,
    name: String,
}

/// The planner side: sends setpoints and commands (each followed by a wake-up of the writer),
/// receives command results and vehicle state.
pub struct OnboardPorts {
    setpoints: Sender<SetpointSample>,
    commands: Sender<CommandSample>,
    wakeup: Wake,
    pub results: Receiver<CommandResultSample>,
    pub state: Receiver<VehicleStateSample>,
}

impl OnboardPorts {
    fn wake(&self) -> Result<(), IpcError> {
        self.wakeup
            .port
            .notify()
            .map(|_| ())
            .map_err(|e| IpcError::Send {
                service: self.wakeup.name.clone(),
                reason: format!("{e:?}"),
            })
    }

    pub fn send_setpoint(&self, setpoint: SetpointSample) -> Result<(), IpcError> {
        self.setpoints.send(setpoint)?;
        self.wake()
    }

    pub fn send_command(&self, command: CommandSample) -> Result<(), IpcError> {
        self.commands.send(command)?;
        self.wake()
    }
}

/// iceoryx2's Unix event (its default on Linux) hands a wait's timeout to the socket's
/// `SO_RCVTIMEO` in whole microseconds, and there zero means "wait for ever": a shorter
/// timeout would block until the next notification, which never comes while the planner is
/// silent (and then the writer would stop streaming its hold and its heartbeat).
pub const SHORTEST_TIMED_WAIT: Duration = Duration::from_micros(1);

/// The writer side.
pub struct WriterPorts {
    pub setpoints: Receiver<SetpointSample>,
    pub commands: Receiver<CommandSample>,
    wakeup: Listener<Svc>,
    wake_name: String,
    results: Sender<CommandResultSample>,
    state: Sender<VehicleStateSample>,
}

impl WriterPorts {
    /// Blocks until the planner side signals new data or `timeout` passes; true when woken.
    /// A timeout under [`SHORTEST_TIMED_WAIT`] (a deadline already due) only polls.
    pub fn wait_for_wakeup(&self, timeout: Duration) -> Result<bool, IpcError> {
        let mut woken = false;
        let on_event = |_| woken = true;
        let waited = if timeout < SHORTEST_TIMED_WAIT {
            self.wakeup.try_wait(on_event)
        } else {
            self.wakeup.timed_wait(on_event, timeout)
        };
        waited.map_err(|e| IpcError::Receive {
            service: self.wake_name.clone(),
            reason: format!("{e:?}"),
        })?;
        Ok(woken)
    }

    pub fn publish_state(&self, state: VehicleStateSample) -> Result<(), IpcError> {
        self.state.send(state)
    }

    pub fn publish_result(&self, result: CommandResultSample) -> Result<(), IpcError> {
        self.results.send(result)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use tacos_shared::ipc::CommandKind;

    fn unique_swarm() -> SwarmId {
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map(|d| d.subsec_nanos())
            .unwrap_or(0);
        SwarmId::new(format!("t{}x{nanos}", std::process::id())).expect("valid id")
    }

    /// Both ends of one drone's services, each on a node of its own as in the two processes.
    struct Ends {
        onboard: OnboardPorts,
        writer: WriterPorts,
        _nodes: [IpcNode; 2],
    }

    fn ends() -> Ends {
        let swarm = unique_swarm();
        let drone = DroneId::new("alfa").expect("valid id");
        let onboard_node = IpcNode::new(&swarm, &drone).expect("node");
        let writer_node = IpcNode::new(&swarm, &drone).expect("node");
        Ends {
            writer: writer_node.writer_ports().expect("writer ports"),
            onboard: onboard_node.onboard_ports().expect("onboard ports"),
            _nodes: [onboard_node, writer_node],
        }
    }

    #[test]
    fn setpoints_commands_and_state_cross_over() {
        let ends = ends();
        let (onboard, writer) = (&ends.onboard, &ends.writer);

        let sp = SetpointSample {
            seq: 3,
            position: [1.0, 2.0, 3.0],
            ..Default::default()
        };
        onboard.send_setpoint(sp).expect("send");
        assert!(
            writer
                .wait_for_wakeup(Duration::from_secs(2))
                .expect("wait")
        );
        assert_eq!(writer.setpoints.latest().expect("recv"), Some(sp));

        onboard
            .send_command(CommandSample::new(9, CommandKind::Takeoff, 10.0))
            .expect("send");
        let cmds = writer.commands.drain().expect("recv");
        assert_eq!(cmds.len(), 1);
        assert_eq!(cmds[0].kind(), Some(CommandKind::Takeoff));

        let state = VehicleStateSample {
            link_ok: 1,
            position: [4.0, 5.0, 6.0],
            ..Default::default()
        };
        writer.publish_state(state).expect("publish");
        assert_eq!(onboard.state.latest().expect("recv"), Some(state));
    }

    /// A loop whose deadline has already passed asks for a zero wait: it must come back at
    /// once, not sleep until the planner next speaks.
    #[test]
    fn a_wait_whose_deadline_has_passed_returns_at_once() {
        let (done_tx, done_rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let ends = ends();
            let waits = [
                Duration::ZERO,
                Duration::from_nanos(999),
                Duration::from_millis(20),
            ];
            let results: Vec<_> = waits
                .into_iter()
                .map(|t| ends.writer.wait_for_wakeup(t).map_err(|e| e.to_string()))
                .collect();
            let _ = done_tx.send(results);
        });
        let results = done_rx
            .recv_timeout(Duration::from_secs(5))
            .expect("a wait with a spent deadline blocked (SO_RCVTIMEO 0 waits for ever)");
        assert_eq!(results, vec![Ok(false), Ok(false), Ok(false)]);
    }
}
