#!/usr/bin/env python3
"""A fake PX4 autopilot that checks tacos-px4's MAVLink with code that is not ours (pymavlink).

It plays the autopilot the writer talks to the way PX4 main SITL (SIH) does: binds a UDP port,
sends HEARTBEAT at 1 Hz with PX4's custom mode (boots in AUTO.LOITER) and system_status (UNINIT
for --ready-after seconds, then STANDBY, ACTIVE when armed), GLOBAL_POSITION_INT and
HOME_POSITION with altitudes above mean sea level (--ground-amsl, SIH's 489.4 m),
LOCAL_POSITION_NED and EXTENDED_SYS_STATE (the vehicle sits on the ground at its origin), and
answers every COMMAND_LONG with COMMAND_ACKs addressed to the sender as PX4 does: an ARM before
it is ready is TEMPORARILY_REJECTED ("Preflight Fail: heading estimate invalid"), DO_SET_MODE is
acked twice (ACCEPTED from the MAVLink receiver, then the mode's result), NAV_TAKEOFF's param7 is
AMSL (a value below the ground is ACCEPTED with "Already higher than takeoff altitude" and
counted as a problem: on PX4 the vehicle would not climb), SET_MESSAGE_INTERVAL and
REQUEST_MESSAGE are honoured for the messages it sends. It keeps a table of PX4's defaults of
the parameters the writer touches and answers the parameter protocol as PX4 does
(PARAM_REQUEST_READ by name or index and PARAM_REQUEST_LIST with PARAM_VALUE, PARAM_SET with
an echo of the new value, INT32 values carried byte for byte in the float field, no answer for
an unknown name; a PARAM_SET whose param_type is not the parameter's is a problem, since PX4
copies the bytes as they come), and the mission protocol for the geofence (MISSION_COUNT →
MISSION_REQUEST_INT per item → MISSION_ACK; MISSION_REQUEST_LIST → MISSION_COUNT →
MISSION_ITEM_INT per MISSION_REQUEST_INT). A fence that is not one inclusion polygon around the
vehicle, and an ARM before the parameters and the fence were confirmed, are problems. Every
byte the writer sends is
decoded by pymavlink's strict (non-robust) parser: a bad prefix, CRC, length or an unknown message
is a failure, and so is a datagram with leftover bytes, a MAVLink 1 frame, or a message the writer
has no business sending.

It checks the SET_POSITION_TARGET_LOCAL_NED stream: frame MAV_FRAME_LOCAL_NED, addressed to this
autopilot, position/velocity/acceleration used, rate at least --min-rate, and every position (and
velocity, when given) equal to --setpoint-enu converted to NED relative to --home.

Before the first of those, a hold at the vehicle's own position (its origin) is accepted: the
writer streams one once it knows where the vehicle is and no planner setpoint has come yet.
It runs for --duration seconds after the first expected setpoint (or gives up after --timeout), prints one
JSON summary line on stdout, and exits 0 when no problem was found, 1 otherwise (2 on bad usage).
"""

import argparse
import json
import math
import socket
import struct
import sys
import time

from pymavlink.dialects.v20 import common as mavlink

ALLOWED = {
    "HEARTBEAT", "SET_POSITION_TARGET_LOCAL_NED", "COMMAND_LONG",
    "PARAM_REQUEST_READ", "PARAM_REQUEST_LIST", "PARAM_SET",
    "MISSION_COUNT", "MISSION_ITEM_INT", "MISSION_REQUEST_LIST", "MISSION_REQUEST_INT", "MISSION_ACK",
}
INT32 = mavlink.MAV_PARAM_TYPE_INT32
REAL32 = mavlink.MAV_PARAM_TYPE_REAL32
# PX4's defaults of the parameters the writer touches (measured on PX4 SITL), in index order.
PX4_PARAMS = [
    ("COM_OBL_RC_ACT", INT32, 0),
    ("COM_OF_LOSS_T", REAL32, 1.0),
    ("NAV_DLL_ACT", INT32, 0),
    ("COM_RCL_EXCEPT", INT32, 0),
    ("NAV_RCL_ACT", INT32, 2),
    ("COM_RC_IN_MODE", INT32, 1),
    ("GF_ACTION", INT32, 2),
    ("GF_MAX_VER_DIST", REAL32, 0.0),
]
FENCE = mavlink.MAV_MISSION_TYPE_FENCE
FENCE_COMMANDS = range(5000, 5005)
POLYGON_VERTEX = (mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION, mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_EXCLUSION)
# POSITION_TARGET_TYPEMASK bits for x..az (ignore flags); all must be clear.
PVA_IGNORE_BITS = 0x1FF
YAW_IGNORE = 1024
PX4_HOLD = (4 << 16) | (3 << 24)  # AUTO.LOITER
PX4_TAKEOFF = (4 << 16) | (2 << 24)
TOLERANCE = 1e-3
# SIH's default origin.
ORIGIN_LAT_E7 = 473977420
ORIGIN_LON_E7 = 85455940
# Default stream periods (s) of PX4's onboard link; HEARTBEAT's is fixed.
DEFAULT_PERIODS = {
    "HEARTBEAT": 1.0,
    "GLOBAL_POSITION_INT": 0.02,
    "LOCAL_POSITION_NED": 1.0 / 30.0,
    "EXTENDED_SYS_STATE": 0.2,
    "HOME_POSITION": 2.0,
}
MESSAGE_IDS = {0: "HEARTBEAT", 32: "LOCAL_POSITION_NED", 33: "GLOBAL_POSITION_INT", 242: "HOME_POSITION", 245: "EXTENDED_SYS_STATE"}


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


def int_to_wire(v):
    """An INT32 parameter in PARAM_VALUE's float field: its four bytes, as PX4 sends it."""
    return struct.unpack("<f", struct.pack("<i", v))[0]


def int_from_wire(f):
    return struct.unpack("<i", struct.pack("<f", f))[0]


def text_of(raw):
    if isinstance(raw, bytes):
        raw = raw.decode("ascii", "replace")
    return raw.split("\0", 1)[0]


def inside(polygon, lat, lon):
    """Whether (lat, lon) is inside the polygon of (lat, lon) vertices (ray casting)."""
    hit = False
    for (a_lat, a_lon), (b_lat, b_lon) in zip(polygon, polygon[1:] + polygon[:1]):
        if (a_lon > lon) != (b_lon > lon):
            at = a_lat + (lon - a_lon) * (b_lat - a_lat) / (b_lon - a_lon)
            if lat < at:
                hit = not hit
    return hit


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
    ap.add_argument("--ready-after", type=float, default=1.0, help="seconds before ARM is accepted (PX4's health checks; default 1)")
    ap.add_argument("--ground-amsl", type=float, default=489.4, help="the vehicle's altitude above mean sea level, m (SIH's default)")
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
    custom_mode = PX4_HOLD
    periods = dict(DEFAULT_PERIODS)
    next_send = {name: 0.0 for name in periods}
    ready_announced = False
    takeoffs = []
    params = [[name, kind, value] for name, kind, value in PX4_PARAMS]
    param_sets = []
    unknown_params = set()
    fence = []
    fence_upload = None  # [count, items, partner]
    fence_results = []
    fence_read_back = False
    setup_confirmed_at = None
    last_param_at = None
    arm_attempts = []

    def problem(text):
        if len(problems) < 50:
            problems.append(text)

    def send(msg):
        try:
            sock.sendto(msg.pack(out), writer)
        except OSError:
            pass  # the writer may not be up yet; PX4 does not care either

    text_ids = iter(range(1, 1 << 30))

    def say(severity, text):
        # PX4 sends texts over 50 bytes in chunks sharing a non-zero id.
        raw = text.encode("ascii")
        if len(raw) <= 50:
            send(out.statustext_encode(severity, raw, 0, 0))
            return
        text_id = (next(text_ids) - 1) % 65535 + 1
        for seq, at in enumerate(range(0, len(raw) + 1, 50)):
            send(out.statustext_encode(severity, raw[at:at + 50], text_id, seq))

    start = time.monotonic()
    first_setpoint = None

    def ready():
        return time.monotonic() - start >= args.ready_after

    def can_arm():
        if not ready():
            return False
        if custom_mode == PX4_HOLD or custom_mode == PX4_TAKEOFF:
            return True
        if custom_mode == 6 << 16:  # OFFBOARD: needs setpoints within COM_OF_LOSS_T
            return bool(setpoint_times) and time.monotonic() - setpoint_times[-1] <= 1.0
        return False

    def message(name):
        boot_ms = int((time.monotonic() - start) * 1000) & 0xFFFFFFFF
        ground_mm = int(round(args.ground_amsl * 1000))
        if name == "HEARTBEAT":
            base = mavlink.MAV_MODE_FLAG_CUSTOM_MODE_ENABLED | (mavlink.MAV_MODE_FLAG_SAFETY_ARMED if armed else 0)
            status = mavlink.MAV_STATE_ACTIVE if armed else (mavlink.MAV_STATE_STANDBY if can_arm() else mavlink.MAV_STATE_UNINIT)
            return out.heartbeat_encode(mavlink.MAV_TYPE_QUADROTOR, mavlink.MAV_AUTOPILOT_PX4, base, custom_mode, status)
        if name == "GLOBAL_POSITION_INT":
            return out.global_position_int_encode(boot_ms, ORIGIN_LAT_E7, ORIGIN_LON_E7, ground_mm, 0, 0, 0, 0, 0)
        if name == "LOCAL_POSITION_NED":
            return out.local_position_ned_encode(boot_ms, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        if name == "EXTENDED_SYS_STATE":
            return out.extended_sys_state_encode(mavlink.MAV_VTOL_STATE_UNDEFINED, mavlink.MAV_LANDED_STATE_ON_GROUND)
        return out.home_position_encode(ORIGIN_LAT_E7, ORIGIN_LON_E7, ground_mm, 0.0, 0.0, 0.0, [1.0, 0.0, 0.0, 0.0], 0.0, 0.0, 0.0)

    def param_index(name):
        for i, p in enumerate(params):
            if p[0] == name:
                return i
        unknown_params.add(name)
        return None

    def send_param(i):
        name, kind, value = params[i]
        wire = int_to_wire(value) if kind == INT32 else float(value)
        send(out.param_value_encode(name.encode("ascii"), wire, kind, len(params), i))

    def params_and_fence(m, name):
        """PX4's parameter and mission protocols (the geofence)."""
        nonlocal fence, fence_upload, fence_read_back, setup_confirmed_at, last_param_at
        src = (m.get_srcSystem(), m.get_srcComponent())
        if name.startswith("PARAM_"):
            last_param_at = time.monotonic()
        if hasattr(m, "target_system") and (m.target_system, m.target_component) != (args.sysid, 1):
            problem("%s addressed to %d/%d" % (name, m.target_system, m.target_component))
        if name == "PARAM_REQUEST_READ":
            i = param_index(text_of(m.param_id)) if m.param_index < 0 else m.param_index
            if i is not None and 0 <= i < len(params):
                send_param(i)
        elif name == "PARAM_REQUEST_LIST":
            for i in range(len(params)):
                send_param(i)
        elif name == "PARAM_SET":
            pname = text_of(m.param_id)
            i = param_index(pname)
            if i is None:
                return
            kind = params[i][1]
            if m.param_type != kind:
                problem("PARAM_SET %s with param_type %d, but it is %d: PX4 would copy the bytes as they are"
                        % (pname, m.param_type, kind))
            params[i][2] = int_from_wire(m.param_value) if kind == INT32 else m.param_value
            param_sets.append(pname)
            send_param(i)
        elif m.mission_type != FENCE:
            problem("%s for mission type %d: the writer only uploads a geofence" % (name, m.mission_type))
        elif name == "MISSION_COUNT":
            if m.count == 0:
                fence = []
                fence_upload = None
                fence_results.append(mavlink.MAV_MISSION_ACCEPTED)
                send(out.mission_ack_encode(src[0], src[1], mavlink.MAV_MISSION_ACCEPTED, FENCE))
            else:
                # A repeated count restarts the upload.
                fence_upload = [m.count, [], src]
                send(out.mission_request_int_encode(src[0], src[1], 0, FENCE))
        elif name == "MISSION_ITEM_INT":
            if fence_upload is None:
                problem("MISSION_ITEM_INT %d outside an upload" % m.seq)
                return
            count, items, _ = fence_upload
            if m.seq + 1 == len(items):
                return  # a repeat: its request is out already
            if m.seq != len(items):
                fence_upload = None
                fence_results.append(mavlink.MAV_MISSION_INVALID_SEQUENCE)
                send(out.mission_ack_encode(src[0], src[1], mavlink.MAV_MISSION_INVALID_SEQUENCE, FENCE))
                return
            items.append(m)
            if len(items) < count:
                send(out.mission_request_int_encode(src[0], src[1], len(items), FENCE))
                return
            fence_upload = None
            result = mavlink.MAV_MISSION_ACCEPTED
            for it in items:
                if it.command not in FENCE_COMMANDS:
                    result = mavlink.MAV_MISSION_UNSUPPORTED
                elif it.frame not in (mavlink.MAV_FRAME_GLOBAL, mavlink.MAV_FRAME_GLOBAL_INT):
                    result = mavlink.MAV_MISSION_UNSUPPORTED_FRAME
                elif it.command in POLYGON_VERTEX and not it.param1 >= 3:
                    result = mavlink.MAV_MISSION_INVALID_PARAM1
            if result == mavlink.MAV_MISSION_ACCEPTED:
                fence = items
                polygon = [(it.x, it.y) for it in items]
                if any(it.command != mavlink.MAV_CMD_NAV_FENCE_POLYGON_VERTEX_INCLUSION or it.param1 != count
                       for it in items):
                    problem("the fence is not one inclusion polygon of %d vertices" % count)
                elif not inside(polygon, ORIGIN_LAT_E7, ORIGIN_LON_E7):
                    problem("the fence %s does not contain the vehicle" % polygon)
            else:
                problem("fence upload refused with MAV_MISSION_RESULT %d" % result)
            fence_results.append(result)
            send(out.mission_ack_encode(src[0], src[1], result, FENCE))
        elif name == "MISSION_REQUEST_LIST":
            send(out.mission_count_encode(src[0], src[1], len(fence), FENCE))
        elif name == "MISSION_REQUEST_INT":
            if m.seq >= len(fence):
                send(out.mission_ack_encode(src[0], src[1], mavlink.MAV_MISSION_INVALID_SEQUENCE, FENCE))
                return
            it = fence[m.seq]
            send(out.mission_item_int_encode(src[0], src[1], it.seq, it.frame, it.command, it.current,
                                             it.autocontinue, it.param1, it.param2, it.param3, it.param4,
                                             it.x, it.y, it.z, FENCE))
        elif name == "MISSION_ACK":
            if fence and m.type == mavlink.MAV_MISSION_ACCEPTED:
                fence_read_back = True
                setup_confirmed_at = time.monotonic()

    def answer(m):
        """The results of a COMMAND_LONG, one per COMMAND_ACK, in order; may send texts first."""
        nonlocal armed, custom_mode
        cmd = m.command
        if cmd == mavlink.MAV_CMD_COMPONENT_ARM_DISARM:
            if m.param1 == 1.0:
                arm_attempts.append(time.monotonic())
            if m.param1 != 1.0:
                armed = False
                return [mavlink.MAV_RESULT_ACCEPTED]
            if armed:
                return [mavlink.MAV_RESULT_ACCEPTED]
            if not ready():
                say(mavlink.MAV_SEVERITY_CRITICAL, "Preflight Fail: heading estimate invalid")
            if not can_arm():
                say(mavlink.MAV_SEVERITY_CRITICAL, "Arming denied: Resolve system health failures first")
                return [mavlink.MAV_RESULT_TEMPORARILY_REJECTED]
            armed = True
            return [mavlink.MAV_RESULT_ACCEPTED]
        if cmd == mavlink.MAV_CMD_NAV_TAKEOFF:
            takeoffs.append(m.param7)
            if math.isfinite(m.param7) and m.param7 < args.ground_amsl:
                say(mavlink.MAV_SEVERITY_CRITICAL, "Already higher than takeoff altitude")
                problem("NAV_TAKEOFF param7 %.2f is below the vehicle's %.2f m AMSL: PX4 reads it as AMSL and would not climb"
                        % (m.param7, args.ground_amsl))
            custom_mode = PX4_TAKEOFF
            return [mavlink.MAV_RESULT_ACCEPTED]
        if cmd == mavlink.MAV_CMD_DO_SET_MODE:
            if not all(math.isfinite(x) and 0 <= x <= 255 for x in (m.param1, m.param2, m.param3)):
                return [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_DENIED]
            wanted = (int(m.param2) << 16) | ((int(m.param3) if int(m.param2) == 4 else 0) << 24)
            fresh = bool(setpoint_times) and time.monotonic() - setpoint_times[-1] <= 0.5
            if armed and wanted == 6 << 16 and custom_mode != wanted and not fresh:
                say(mavlink.MAV_SEVERITY_CRITICAL, "Switching to Offboard is currently not available")
                return [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_TEMPORARILY_REJECTED]
            custom_mode = wanted
            return [mavlink.MAV_RESULT_ACCEPTED, mavlink.MAV_RESULT_ACCEPTED]
        if cmd == mavlink.MAV_CMD_SET_MESSAGE_INTERVAL:
            name = MESSAGE_IDS.get(int(m.param1 + 0.5)) if math.isfinite(m.param1) else None
            if name is None or name == "HEARTBEAT":
                return [mavlink.MAV_RESULT_FAILED]
            if m.param2 < -1e-5:
                periods[name] = None
            elif m.param2 > 1e-5:
                periods[name] = m.param2 * 1e-6
            else:
                periods[name] = DEFAULT_PERIODS[name]
            next_send[name] = time.monotonic() - start
            return [mavlink.MAV_RESULT_ACCEPTED]
        if cmd == mavlink.MAV_CMD_REQUEST_MESSAGE:
            name = MESSAGE_IDS.get(int(round(m.param1))) if math.isfinite(m.param1) else None
            if name is None:
                return [mavlink.MAV_RESULT_DENIED]
            send(message(name))
            return [mavlink.MAV_RESULT_ACCEPTED]
        return [mavlink.MAV_RESULT_ACCEPTED]

    while True:
        now = time.monotonic()
        if first_setpoint is not None and now - first_setpoint >= args.duration:
            break
        if now - start >= args.timeout:
            if first_setpoint is None:
                problem("no SET_POSITION_TARGET_LOCAL_NED at the expected point within %.1f s" % args.timeout)
            break
        since = now - start
        for name, period in periods.items():
            if period is not None and since >= next_send[name]:
                send(message(name))
                next_send[name] = max(next_send[name] + period, since)
        if not ready_announced and ready():
            ready_announced = True
            say(mavlink.MAV_SEVERITY_INFO, "Ready for takeoff!")
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
                setpoint_times.append(at)
                pos = (m.x, m.y, m.z)
                vel = (m.vx, m.vy, m.vz)
                # Before the planner's first setpoint the writer holds the vehicle where it is
                # (here, at its origin), once it knows where that is: the watch starts with
                # the planner's stream, and only a hold at the vehicle may come before it.
                planner_setpoint = close(pos, expected_ned)
                if first_setpoint is None and planner_setpoint:
                    first_setpoint = at
                hold_before = first_setpoint is None and close(pos, (0.0, 0.0, 0.0)) and close(vel, (0.0, 0.0, 0.0))
                frames.add(m.coordinate_frame)
                last_setpoint = {"ned": pos, "velocity_ned": vel, "type_mask": m.type_mask, "yaw": m.yaw}
                if m.coordinate_frame != mavlink.MAV_FRAME_LOCAL_NED:
                    problem("setpoint frame %d, not MAV_FRAME_LOCAL_NED" % m.coordinate_frame)
                if (m.target_system, m.target_component) != (args.sysid, 1):
                    problem("setpoint addressed to %d/%d" % (m.target_system, m.target_component))
                if m.type_mask & PVA_IGNORE_BITS:
                    problem("setpoint type_mask %#x ignores position/velocity/acceleration" % m.type_mask)
                if not planner_setpoint and not hold_before:
                    problem("setpoint NED %s, expected %s" % (pos, expected_ned))
                if not hold_before and expected_vel is not None and not close(vel, expected_vel) and not close(vel, (0.0, 0.0, 0.0)):
                    problem("setpoint velocity NED %s, expected %s (or zero in a hold)" % (vel, expected_vel))
            elif name.startswith("PARAM_") or name.startswith("MISSION_"):
                params_and_fence(m, name)
            elif name == "COMMAND_LONG":
                commands.append({"command": m.command, "confirmation": m.confirmation,
                                 "param1": m.param1, "param2": m.param2, "param7": m.param7})
                if (m.target_system, m.target_component) != (args.sysid, 1):
                    problem("COMMAND_LONG addressed to %d/%d" % (m.target_system, m.target_component))
                for result in answer(m):
                    send(out.command_ack_encode(m.command, result, 0, 0, m.get_srcSystem(), m.get_srcComponent()))

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
    if arm_attempts and fence_results and (setup_confirmed_at is None or arm_attempts[0] < setup_confirmed_at):
        problem("ARM before the geofence was uploaded and read back")
    if arm_attempts and last_param_at is not None and arm_attempts[0] < last_param_at:
        problem("ARM while the parameters were still being read or set")

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
        "takeoff_param7": takeoffs,
        "armed": armed,
        "custom_mode": custom_mode,
        "params": {name: value for name, _, value in params},
        "param_sets": param_sets,
        "unknown_params": sorted(unknown_params),
        "fence": [[it.x, it.y] for it in fence],
        "fence_results": fence_results,
        "fence_read_back": fence_read_back,
        "pymavlink_receive_errors": parser.total_receive_errors,
    }
    print(json.dumps(summary), flush=True)
    return 0 if not problems else 1


if __name__ == "__main__":
    sys.exit(main())
