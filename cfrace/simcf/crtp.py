"""CRTP services of one simulated Crazyflie: bytes in, bytes out (no sockets here).

Wire format of cflib's UDP driver (cflib/crtp/udpdriver.py, 0.1.34): one datagram = one CRTP
packet, byte 0 = (port << 4) | 0b1100 | channel, then up to 30 payload bytes; no first special
datagram. Replies follow the firmware's formats (read from crazyflie-firmware: crtpservice.c,
platformservice.c, param_logic.c, log.c, crtp_supervisor.c, crtp_mem.c) for what cflib's connect
sequence uses: link source ("Bitcraze Crazyflie"), protocol version, log reset + log TOC (v2),
memory count, param TOC (v2) and the read of every parameter, and echo pings every 100 ms.
"""

from __future__ import annotations

import errno
import math
import struct
import threading
import zlib

from cfrace.simcf import memory
from cfrace.simcf.firmware import SimFleet
from cfrace.simcf.packets import (EXT_POSE, EXT_POSE_PACKED, EXT_POSITION_PACKED, GENERIC_TYPES,  # noqa: F401
                                  LOG_TYPES, LOG_VARS, LogBlock, pack_value, decode_generic, decode_high_level,
                                  quat_decompress)
from cfrace.simcf.params import FIRMWARE_RELEASE, PARAM_BY_NAME, PARAM_TYPES, PARAMS, device_type_name

PROTOCOL_VERSION = 12     #: what the current firmware reports; cflib 0.1.34 needs >= 12 for the supervisor port
MAX_PAYLOAD = 30

# ports
CONSOLE, PARAM, COMMANDER, MEM, LOG, LOCALIZATION, GENERIC_COMMANDER, HL_COMMANDER, SUPERVISOR = 0, 2, 3, 4, 5, 6, 7, 8, 9
PLATFORM, LINK = 13, 15

LOG_MAX_BLOCKS = 16
LOG_MAX_OPS = 128
LOG_MAX_LEN = 26      #: bytes of variable data per log packet


def header(port: int, channel: int) -> int:
    return ((port & 0x0F) << 4) | 0x0C | (channel & 0x03)


def packet(port: int, channel: int, payload: bytes = b"") -> bytes:
    if len(payload) > MAX_PAYLOAD:
        raise ValueError(f"CRTP payload of {len(payload)} bytes > {MAX_PAYLOAD}")
    return bytes([header(port, channel)]) + bytes(payload)


def _toc_item(index: int, type_byte: int, name: str) -> bytes:
    group, var = name.split(".")
    return struct.pack("<HB", index, type_byte) + group.encode() + b"\0" + var.encode() + b"\0"


def _param_type_byte(spec) -> int:
    return PARAM_TYPES[spec.ctype][0] | (0x40 if spec.readonly else 0)


PARAM_TOC = [_toc_item(k, _param_type_byte(p), p.name) for k, p in enumerate(PARAMS)]
LOG_TOC = [_toc_item(k, t, n) for k, (n, t) in enumerate(LOG_VARS)]
PARAM_CRC = zlib.crc32(b"".join(PARAM_TOC))
LOG_CRC = zlib.crc32(b"".join(LOG_TOC))


class CrtpEndpoint:
    """The CRTP side of drone ``index`` of a SimFleet: ``handle(datagram) -> [reply datagrams]``."""

    def __init__(self, fleet: SimFleet, index: int):
        self.fleet = fleet
        self.index = index
        self.blocks: dict[int, LogBlock] = {}
        self.warned: set[str] = set()
        self.rx = 0          #: datagrams received
        self.tx = 0          #: datagrams produced
        self.setpoints = 0   #: legacy setpoints received
        self._lock = threading.Lock()   # handle() runs on the receiver thread, due_packets() on the clock

    # -------------------------------------------------------------- dispatch
    def handle(self, data: bytes) -> list[bytes]:
        with self._lock:
            return self._handle(data)

    def _handle(self, data: bytes) -> list[bytes]:
        self.rx += 1
        if not data:
            return []
        self.fleet.note_packet(self.index)
        port, channel, payload = data[0] >> 4, data[0] & 0x03, bytes(data[1:])
        if data[0] == 0xFF and not payload:
            return self._out([packet(LINK, 3)])        # scan probe: answer anything
        handler = {LINK: self._link, PLATFORM: self._platform, PARAM: self._param, LOG: self._log,
                   MEM: self._mem, COMMANDER: self._commander, GENERIC_COMMANDER: self._generic,
                   SUPERVISOR: self._supervisor, LOCALIZATION: self._localization,
                   HL_COMMANDER: self._high_level}.get(port)
        if handler is None:
            return []
        return self._out(handler(channel, payload) or [])

    def _out(self, replies: list[bytes]) -> list[bytes]:
        self.tx += len(replies)
        return replies

    def _warn_once(self, what: str) -> list[bytes]:
        if what in self.warned:
            return []
        self.warned.add(what)
        return console_packets(f"SIMCF: {what} is not emulated, ignored\n")

    # -------------------------------------------------------------- services
    def _link(self, channel: int, payload: bytes) -> list[bytes]:
        if channel == 0:                                   # echo (cflib pings every 100 ms)
            return [packet(LINK, 0, payload)]
        if channel == 1:                                   # source: the magic string, 30 bytes
            return [packet(LINK, 1, b"Bitcraze Crazyflie".ljust(MAX_PAYLOAD, b"\0"))]
        return []                                          # sink and others: ignored

    def _platform(self, channel: int, payload: bytes) -> list[bytes]:
        if not payload:
            return []
        cmd = payload[0]
        if channel == 0:
            if cmd == 1:                                   # legacy arming request
                ok = self.fleet.arm(self.index, bool(payload[1]) if len(payload) > 1 else False)
                return [packet(PLATFORM, 0, bytes([cmd, int(ok), int(self.fleet.status(self.index)["armed"])]))]
            if cmd == 2:                                   # legacy crash recovery
                ok = self.fleet.recover(self.index)
                return [packet(PLATFORM, 0, bytes([cmd, int(ok), int(ok)]))]
            if cmd == 3:                                   # user notification: empty answer
                return [packet(PLATFORM, 0)]
            return [packet(PLATFORM, 0, payload)]          # continuous wave etc.: echoed
        if channel == 1:
            if cmd == 0:
                return [packet(PLATFORM, 1, struct.pack("<Bi", 0, PROTOCOL_VERSION))]
            # platformservice.c versionCommandProcess: the string after the command byte, no terminator
            if cmd == 1:
                return [packet(PLATFORM, 1, bytes([1]) + FIRMWARE_RELEASE.encode())]
            if cmd == 2:
                return [packet(PLATFORM, 1, bytes([2]) + device_type_name(self.fleet.arming_required).encode())]
        return []

    def _param(self, channel: int, payload: bytes) -> list[bytes]:
        if not payload:
            return []
        if channel == 0:                                   # TOC (v2 commands only, protocol >= 4)
            if payload[0] == 3:
                return [packet(PARAM, 0, struct.pack("<BHI", 3, len(PARAM_TOC), PARAM_CRC))]
            if payload[0] == 2 and len(payload) >= 3:
                ident = struct.unpack_from("<H", payload, 1)[0]
                body = PARAM_TOC[ident] if ident < len(PARAM_TOC) else b""
                return [packet(PARAM, 0, bytes([2]) + body)]
            return []
        if channel in (1, 2):                              # read / write
            if len(payload) < 2:
                return []
            ident = struct.unpack_from("<H", payload, 0)[0]
            if ident >= len(PARAMS):
                return [packet(PARAM, channel, payload[:2] + bytes([errno.ENOENT]))]
            spec = PARAMS[ident]
            fmt = PARAM_TYPES[spec.ctype][1]
            if channel == 2:
                if spec.readonly:
                    return []                              # the firmware ignores writes to RO params
                try:
                    (value,) = struct.unpack(fmt, payload[2:2 + struct.calcsize(fmt)])
                except struct.error:
                    return []
                stored = self.fleet.set_param(self.index, spec.name, value)
                return [packet(PARAM, 2, payload[:2] + struct.pack(fmt, stored))]
            value = self.fleet.get_param(self.index, spec.name)
            return [packet(PARAM, 1, payload[:2] + b"\0" + struct.pack(fmt, value))]
        return self._param_misc(payload)

    def _param_misc(self, payload: bytes) -> list[bytes]:
        cmd = payload[0]
        if cmd == 0:                                       # set by name: group\0name\0 type value
            parts = payload[1:].split(b"\0", 2)
            if len(parts) < 3 or not parts[2]:
                return []
            name = f"{parts[0].decode(errors='replace')}.{parts[1].decode(errors='replace')}"
            prefix = payload[:1] + parts[0] + b"\0" + parts[1] + b"\0"
            spec = PARAM_BY_NAME.get(name)
            if spec is None:
                return [packet(PARAM, 3, prefix + bytes([errno.ENOENT]))]
            if spec.readonly:
                return [packet(PARAM, 3, prefix + bytes([errno.EACCES]))]
            fmt = PARAM_TYPES[spec.ctype][1]
            try:
                (value,) = struct.unpack(fmt, parts[2][1:1 + struct.calcsize(fmt)])
            except struct.error:
                return [packet(PARAM, 3, prefix + bytes([errno.EINVAL]))]
            self.fleet.set_param(self.index, name, value)
            return [packet(PARAM, 3, prefix + b"\0")]
        if len(payload) < 3:
            return []
        ident = struct.unpack_from("<H", payload, 1)[0]
        head = payload[:3]
        if ident >= len(PARAMS):
            return [packet(PARAM, 3, head + bytes([errno.ENOENT]))]
        spec = PARAMS[ident]
        if cmd == 2:                                       # extended type, v1
            return [packet(PARAM, 3, head + b"\0")]
        if cmd == 7:                                       # extended type, v2: status 0, type 0
            return [packet(PARAM, 3, head + b"\0\0")]
        if cmd in (6, 8):                                  # default value v1 / v2
            value = struct.pack(PARAM_TYPES[spec.ctype][1], spec.default)
            return [packet(PARAM, 3, head + (b"\0" if cmd == 8 else b"") + value)]
        if cmd in (3, 4, 5):                               # persistent storage: not available
            return [packet(PARAM, 3, head + bytes([errno.ENOENT]))]
        return []

    def _log(self, channel: int, payload: bytes) -> list[bytes]:
        if not payload:
            return []
        cmd = payload[0]
        if channel == 0:
            if cmd == 3:
                return [packet(LOG, 0, struct.pack("<BHIBB", 3, len(LOG_TOC), LOG_CRC, LOG_MAX_BLOCKS, LOG_MAX_OPS))]
            if cmd == 2 and len(payload) >= 3:
                ident = struct.unpack_from("<H", payload, 1)[0]
                body = LOG_TOC[ident] if ident < len(LOG_TOC) else b""
                return [packet(LOG, 0, bytes([2]) + body)]
            return []
        if channel != 1:
            return []
        block_id = payload[1] if len(payload) > 1 else 0
        ret = self._log_control(cmd, block_id, payload)
        return [packet(LOG, 1, bytes([cmd, block_id, ret]))]

    def _log_control(self, cmd: int, block_id: int, payload: bytes) -> int:
        if cmd == 5:                                       # reset
            self.blocks.clear()
            return 0
        if cmd in (6, 7):                                  # create / append (v2 ops: type, id u16)
            if cmd == 6:
                if block_id in self.blocks:
                    return errno.EEXIST
                if len(self.blocks) >= LOG_MAX_BLOCKS:
                    return errno.ENOMEM
                self.blocks[block_id] = LogBlock()
            block = self.blocks.get(block_id)
            if block is None:
                return errno.ENOENT
            for k in range(2, len(payload) - 2, 3):
                type_byte, var = payload[k], struct.unpack_from("<H", payload, k + 1)[0]
                fetch = type_byte & 0x0F
                if var >= len(LOG_VARS) or fetch not in LOG_TYPES:
                    return errno.ENOENT                    # memory variables (0xFFFF) are not emulated
                if block.length() + LOG_TYPES[fetch][1] > LOG_MAX_LEN:
                    return errno.E2BIG
                if sum(len(b.ops) for b in self.blocks.values()) >= LOG_MAX_OPS:
                    return errno.ENOMEM
                block.ops.append((var, fetch))
            return 0
        block = self.blocks.get(block_id)
        if block is None:
            return errno.ENOENT if cmd in (2, 3, 4, 8) else errno.ENOEXEC
        if cmd in (3, 8):                                  # start (period in 10 ms units / v2 in ms)
            if cmd == 3:
                period_ms = 10 * (payload[2] if len(payload) > 2 else 10)
            else:
                period_ms = struct.unpack_from("<H", payload, 2)[0] if len(payload) >= 4 else 100
            block.period = max(period_ms, 10) / 1000.0
            block.started = True
            block.next_due = self.fleet.time
            return 0
        if cmd == 4:
            block.started = False
            return 0
        if cmd == 2:
            del self.blocks[block_id]
            return 0
        return errno.ENOEXEC

    def _mem(self, channel: int, payload: bytes) -> list[bytes]:
        """The memory subsystem (simcf/memory.py); a malformed request: one console line per kind."""
        with self.fleet.lock:
            answers, line = memory.handle(self.fleet.memories(self.index), channel, payload)
        out = []
        if line and line not in self.warned:
            self.warned.add(line)
            out = console_packets(line + "\n")
        return out + [packet(MEM, ch, p) for ch, p in answers]

    def _commander(self, channel: int, payload: bytes) -> list[bytes]:
        if channel == 0 and len(payload) >= 14:
            roll, pitch, yaw, thrust = struct.unpack_from("<fffH", payload, 0)
            if not all(math.isfinite(v) for v in (roll, pitch, yaw)):
                return self._warn_once("a setpoint with NaN/inf values (dropped; later ones too)")
            self.setpoints += 1
            self.fleet.handle_setpoint(self.index, roll, pitch, yaw, thrust)
        return []

    def _generic(self, channel: int, payload: bytes) -> list[bytes]:
        if not payload:
            return []
        if channel == 1:                                   # meta commands
            if payload[0] == 0 and len(payload) >= 5:      # notify setpoint stop (remain-valid ms: unused)
                self.fleet.notify_setpoint_stop(self.index)
            return []
        if channel != 0:
            return []
        if payload[0] == 0:                                # TYPE_STOP
            self.fleet.stop_setpoint(self.index)
            return []
        try:
            sp = decode_generic(payload[0], payload[1:])
        except struct.error:
            return self._warn_once(f"a generic setpoint of type {payload[0]} with a bad length (dropped)")
        if sp is None:
            return self._warn_once(f"generic setpoint type {payload[0]}")
        try:
            self.fleet.low_level_setpoint(self.index, sp)
        except ValueError:
            return self._warn_once("a setpoint with NaN/inf values (dropped; later ones too)")
        self.setpoints += 1
        return []

    def _high_level(self, channel: int, payload: bytes) -> list[bytes]:
        """Every command is answered as crtp_commander_high_level.c's task does: the packet's first three
        bytes and the command's return code (commands the simulator drops: ENOEXEC)."""
        if channel != 0 or not payload:
            return []
        answer = lambda ret: [packet(HL_COMMANDER, 0, payload[:3].ljust(3, b"\0") + bytes([ret & 0xFF]))]  # noqa: E731
        try:
            decoded = decode_high_level(payload)
        except struct.error:
            return self._warn_once(f"a high-level command {payload[0]} with a bad length (dropped)") + answer(errno.ENOEXEC)
        if decoded is None:
            return self._warn_once(f"high-level command {payload[0]}") + answer(errno.ENOEXEC)
        command, mask, args = decoded
        if not all(math.isfinite(v) for v in args.values() if isinstance(v, float)):
            return self._warn_once("a high-level command with NaN/inf values (dropped)") + answer(errno.ENOEXEC)
        return answer(self.fleet.high_level(self.index, command, mask, **args))

    def _supervisor(self, channel: int, payload: bytes) -> list[bytes]:
        if not payload:
            return []
        cmd = payload[0]
        if channel == 0:
            bits = self.fleet.supervisor_bitfield(self.index)
            if cmd == 0x0C:
                return [packet(SUPERVISOR, 0, struct.pack("<BH", 0x80 | cmd, bits))]
            if 1 <= cmd <= 0x0B:
                return [packet(SUPERVISOR, 0, bytes([0x80 | cmd, (bits >> (cmd - 1)) & 1]))]
            return []
        if channel == 1:
            if cmd == 1 and len(payload) >= 2:
                ok = self.fleet.arm(self.index, bool(payload[1]))
                armed = self.fleet.status(self.index)["armed"]
                return [packet(SUPERVISOR, 1, bytes([0x81, int(ok), int(armed)]))]
            if cmd == 2:                                   # crash recovery request
                ok = self.fleet.recover(self.index)
                return [packet(SUPERVISOR, 1, bytes([0x82, int(ok), int(ok)]))]
            if cmd == 3:
                self.fleet.emergency_stop(self.index, "supervisor emergency stop")
            elif cmd == 4:
                self.fleet.feed_emergency_stop_watchdog(self.index)
        return []

    def _localization(self, channel: int, payload: bytes) -> list[bytes]:
        if channel == 0 and len(payload) >= 12:           # external position x, y, z
            self.fleet.external_position(self.index, struct.unpack_from("<fff", payload, 0))
            return []
        if channel == 1 and payload and payload[0] == EXT_POSE and len(payload) >= 29:
            x, y, z, qx, qy, qz, qw = struct.unpack_from("<7f", payload, 1)
            self.fleet.external_position(self.index, (x, y, z), (qw, qx, qy, qz))
            return []
        # crtp_localization_service.c, extPositionPackedHandler / extPosePackedHandler: items for
        # several drones in one broadcast packet, each drone takes the item with its own radio id
        if channel == EXT_POSITION_PACKED or (channel == 1 and payload and payload[0] == EXT_POSE_PACKED):
            pose = channel == 1
            body = payload[1:] if pose else payload
            size = 11 if pose else 7
            me = self.fleet.radio_id(self.index)
            for k in range(len(body) // size):
                item = struct.unpack_from("<BhhhI" if pose else "<Bhhh", body, k * size)
                pos = tuple(v / 1000.0 for v in item[1:4])
                if item[0] == me:
                    self.fleet.external_position(self.index, pos, quat_decompress(item[4]) if pose else None)
                else:
                    self.fleet.peer_position(self.index, pos)
            return []
        if channel == 1 and payload:
            if payload[0] == 3:
                self.fleet.emergency_stop(self.index, "localization emergency stop")
            elif payload[0] == 4:
                self.fleet.feed_emergency_stop_watchdog(self.index)
        return []

    # -------------------------------------------------------------- outgoing
    def due_packets(self) -> list[bytes]:
        """Log data of the started blocks whose period has elapsed (simulated time), and console
        lines of firmware events."""
        with self._lock:
            return self._due_packets()

    def _due_packets(self) -> list[bytes]:
        out = [p for line in self.fleet.drain_events(self.index) for p in console_packets(line + "\n")]
        t = self.fleet.time
        due = [(bid, b) for bid, b in self.blocks.items() if b.started and t >= b.next_due]
        if due:
            values = self.fleet.log_values(self.index)
            stamp = struct.pack("<I", int(t * 1000.0) & 0xFFFFFF)[:3]
            for bid, block in due:
                data = b"".join(pack_value(fetch, values[LOG_VARS[var][0]]) for var, fetch in block.ops)
                out.append(packet(LOG, 2, bytes([bid]) + stamp + data))
                block.next_due += block.period
                if block.next_due <= t:                    # fell behind: no burst, restart the period
                    block.next_due = t + block.period
        self.tx += len(out)
        return out


def console_packets(text: str) -> list[bytes]:
    raw = text.encode()
    return [packet(CONSOLE, 0, raw[k:k + MAX_PAYLOAD]) for k in range(0, len(raw), MAX_PAYLOAD)]
