#!/usr/bin/env python3
"""A fake PX4 autopilot that checks tacos-px4's MAVLink with code that is not ours (pymavlink).

It plays the autopilot the writer talks to: binds a UDP port, sends HEARTBEATs with a PX4 custom
mode to the writer (as PX4 SITL does to port 14540), and answers every COMMAND_LONG with a
COMMAND_ACK (ACCEPTED; arming on MAV_CMD_COMPONENT_ARM_DISARM). Every byte the writer sends is
decoded by pymavlink's strict (non-robust) parser: a bad prefix, CRC, length or an unknown message
is a failure, and so is a datagram with leftover bytes, a MAVLink 1 frame, or a message the writer
has no business sending.

It checks the SET_POSITION_TARGET_LOCAL_NED stream: frame MAV_FRAME_LOCAL_NED, addressed to this
autopilot, position/velocity/acceleration used, rate at least --min-rate, and every position (and
velocity, when given) equal to --setpoint-enu converted to NED relative to --home.

It runs for --duration seconds after the first setpoint (or gives up after --timeout), prints one
JSON summary line on stdout, and exits 0 when no problem was found, 1 otherwise (2 on bad usage).
"""

import argparse
import json
import math
import socket
import sys
import time

from pymavlink.dialects.v20 import common as mavlink

ALLOWED = {"HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG"}
# POSITION_TARGET_TYPEMASK bits for x..az (ignore flags); all must be clear.
PVA_IGNORE_BITS = 0x1FF
YAW_IGNORE = 1024
PX4_HOLD = (4 << 16) | (3 << 24)  # AUTO.LOITER
TOLERANCE = 1e-3


def triple(raw):
    parts = raw.split(",")
    if len(parts) != 3:
        raise argparse.ArgumentTypeError("expected X,Y,Z")
    try:
        return tuple(float(p) for p in parts)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e))


def host_port(raw):
    host, _, port = raw.rpartition(":")
    try:
        return host, int(port)
    except ValueError as e:
        raise argparse.ArgumentTypeError(str(e))


def enu_to_ned(p, home):
    return (p[1] - home[1], p[0] - home[0], -(p[2] - home[2]))


def enu_vec_to_ned(v):
    return (v[1], v[0], -v[2])


def frame_name(f):
    entry = mavlink.enums["MAV_FRAME"].get(f)
    return entry.name if entry is not None else str(f)


def close(a, b):
    return all(math.isfinite(x) and abs(x - y) <= TOLERANCE for x, y in zip(a, b))


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--writer", type=host_port, required=True, help="tacos-px4's udpin address HOST:PORT")
    ap.add_argument("--bind", type=host_port, default=("127.0.0.1", 0), help="our address (default 127.0.0.1:0)")
    ap.add_argument("--home", type=triple, required=True, help="the writer's --home, world ENU X,Y,Z")
    ap.add_argument("--setpoint-enu", type=triple, required=True, help="the setpoint the planner sends, ENU")
    ap.add_argument("--velocity-enu", type=triple, default=None, help="its velocity, ENU (checked when given)")
    ap.add_argument("--sysid", type=int, default=1, help="our system id (default 1)")
    ap.add_argument("--duration", type=float, default=3.0, help="seconds to watch after the first setpoint")
    ap.add_argument("--timeout", type=float, default=20.0, help="overall limit, seconds")
    ap.add_argument("--min-rate", type=float, default=20.0, help="minimum setpoint rate, Hz")
    ap.add_argument("--expect-command", type=int, action="append", default=[], help="a MAV_CMD that must arrive (repeatable)")
    args = ap.parse_args()

    expected_ned = enu_to_ned(args.setpoint_enu, args.home)
    expected_vel = enu_vec_to_ned(args.velocity_enu) if args.velocity_enu else None

    sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    sock.bind(args.bind)
    sock.settimeout(0.02)
    writer = args.writer

    out = mavlink.MAVLink(None, srcSystem=args.sysid, srcComponent=1)
    parser = mavlink.MAVLink(None)
    parser.robust_parsing = False

    problems = []
    counts = {}
    datagrams = 0
    total_bytes = 0
    setpoint_times = []
    last_setpoint = None
    commands = []
    writer_ids = set()
    seq_gaps = 0
    last_seq = None
    heartbeat_checked = False
    frames = set()
    armed = False

    def problem(text):
        if len(problems) < 50:
            problems.append(text)

    def send(msg):
        try:
            sock.sendto(msg.pack(out), writer)
        except OSError:
            pass  # the writer may not be up yet; PX4 does not care either

    start = time.monotonic()
    next_heartbeat = start
    first_setpoint = None
    while True:
        now = time.monotonic()
        if first_setpoint is not None and now - first_setpoint >= args.duration:
            break
        if now - start >= args.timeout:
            if first_setpoint is None:
                problem("no SET_POSITION_TARGET_LOCAL_NED within %.1f s" % args.timeout)
            break
        if now >= next_heartbeat:
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            send(out.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, PX4_HOLD, mavlink.MAV_STATE_STANDBY))
            next_heartbeat = now + 0.5
        try:
            data, _ = sock.recvfrom(65536)
        except socket.timeout:
            continue
        except OSError:
            continue
        at = time.monotonic()
        datagrams += 1
        total_bytes += len(data)
        if data[:1] != b"\xfd":
            problem("datagram %d does not start with a MAVLink 2 frame (first byte %r)" % (datagrams, data[:1]))
        errors_before = parser.total_receive_errors
        try:
            msgs = parser.parse_buffer(data) or []
        except mavlink.MAVError as e:
            problem("datagram %d: pymavlink parse error: %s" % (datagrams, e))
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = False
            continue
        if parser.total_receive_errors != errors_before:
            problem("datagram %d: pymavlink counted receive errors" % datagrams)
        if parser.buf_len() != 0:
            problem("datagram %d: %d bytes left over after its frames" % (datagrams, parser.buf_len()))
            parser = mavlink.MAVLink(None)
            parser.robust_parsing = False
        if not msgs:
            problem("datagram %d held no message" % datagrams)
        for m in msgs:
            name = m.get_type()
            counts[name] = counts.get(name, 0) + 1
            if name == "BAD_DATA" or name not in ALLOWED:
                problem("unexpected message %s" % name)
                continue
            hdr = m.get_header()
            if hdr.incompat_flags != 0:
                problem("%s has incompat_flags %d" % (name, hdr.incompat_flags))
            writer_ids.add((m.get_srcSystem(), m.get_srcComponent()))
            if last_seq is not None and m.get_seq() != (last_seq + 1) % 256:
                seq_gaps += 1
            last_seq = m.get_seq()
            if name == "HEARTBEAT":
                if m.type != mavlink.MAV_TYPE_ONBOARD_CONTROLLER or m.autopilot != mavlink.MAV_AUTOPILOT_INVALID:
                    problem("writer heartbeat type %d autopilot %d" % (m.type, m.autopilot))
                heartbeat_checked = True
            elif name == "SET_POSITION_TARGET_LOCAL_NED":
                if first_setpoint is None:
                    first_setpoint = at
                setpoint_times.append(at)
                pos = (m.x, m.y, m.z)
                vel = (m.vx, m.vy, m.vz)
                frames.add(m.coordinate_frame)
                last_setpoint = {"ned": pos, "velocity_ned": vel, "type_mask": m.type_mask, "yaw": m.yaw}
                if m.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
                    problem("setpoint frame %d, not MAV_FRAME_LOCAL_NED" % m.coordinate_frame)
                if (m.target_system, m.target_component) != (args.sysid, 1):
                    problem("setpoint addressed to %d/%d" % (m.target_system, m.target_component))
                if m.type_mask & PVA_IGNORE_BITS:
                    problem("setpoint type_mask %#x ignores position/velocity/acceleration" % m.type_mask)
                if not close(pos, expected_ned):
                    problem("setpoint NED %s, expected %s" % (pos, expected_ned))
                if expected_vel is not None and not close(vel, expected_vel) and not close(vel, (0.0, 0.0, 0.0)):
                    problem("setpoint velocity NED %s, expected %s (or zero in a hold)" % (vel, expected_vel))
            elif name == "COMMAND_LONG":
                commands.append({"command": m.command, "confirmation": m.confirmation,
                                 "param1": m.param1, "param2": m.param2, "param7": m.param7})
                if (m.target_system, m.target_component) != (args.sysid, 1):
                    problem("COMMAND_LONG addressed to %d/%d" % (m.target_system, m.target_component))
                if m.command == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
                    armed = m.param1 == 1.0
                send(out.command_ack_encode(m.command, mavlink.MAV_RESULT_ACCEPTED, 0, 0, m.get_srcSystem(), m.get_srcComponent()))

    rate = 0.0
    if len(setpoint_times) >= 2 and setpoint_times[-1] > setpoint_times[0]:
        rate = (len(setpoint_times) - 1) / (setpoint_times[-1] - setpoint_times[0])
    if setpoint_times and rate < args.min_rate:
        problem("setpoint rate %.1f Hz below %.1f Hz" % (rate, args.min_rate))
    max_gap = max((b - a for a, b in zip(setpoint_times, setpoint_times[1:])), default=0.0)
    if not heartbeat_checked:
        problem("no HEARTBEAT from the writer")
    for cmd in args.expect_command:
        if not any(c["command"] == cmd for c in commands):
            problem("expected COMMAND_LONG %d never arrived" % cmd)
    if len(writer_ids) > 1:
        problem("messages from several ids: %s" % sorted(writer_ids))

    summary = {
        "ok": not problems,
        "problems": problems,
        "datagrams": datagrams,
        "bytes": total_bytes,
        "messages": counts,
        "writer_ids": sorted(writer_ids),
        "sequence_gaps": seq_gaps,
        "setpoints": len(setpoint_times),
        "setpoint_rate_hz": round(rate, 2),
        "setpoint_max_gap_ms": round(max_gap * 1000.0, 1),
        "setpoint_frames": sorted(frame_name(f) for f in frames),
        "expected_ned": expected_ned,
        "last_setpoint": last_setpoint,
        "commands": commands,
        "armed": armed,
        "pymavlink_receive_errors": parser.total_receive_errors,
    }
    print(json.dumps(summary), flush=True)
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
