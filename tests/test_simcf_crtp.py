"""CRTP services of the simulated Crazyflie, bytes in / bytes out (no sockets)."""

import errno
import math
import random
import struct

import pytest

from cfrace.simcf import crtp
from cfrace.simcf.controller import ABS, VELOCITY
from cfrace.simcf.crtp import CrtpEndpoint, LOG_VARS, PARAMS, packet
from cfrace.simcf.firmware import SimFleet


@pytest.fixture(scope="module")
def fleet():
    return SimFleet("lemniscate", "cf2x_paper", 2, arming_required=True)


@pytest.fixture
def ep(fleet):
    fleet.reset()
    return CrtpEndpoint(fleet, 0)


def one(replies):
    assert len(replies) == 1, replies
    d = replies[0]
    return d[0] >> 4, d[0] & 3, d[1:]


def test_header_layout():
    assert packet(crtp.COMMANDER, 0)[0] == 0x3C           # (3 << 4) | 0b1100 | 0
    assert packet(crtp.LINK, 1)[0] == 0xFD
    with pytest.raises(ValueError):
        packet(crtp.LINK, 0, bytes(31))


def test_link_source_echo_and_version(ep):
    port, ch, data = one(ep.handle(packet(crtp.LINK, 1, b"\0")))
    assert (port, ch, len(data)) == (15, 1, 30) and data[:18] == b"Bitcraze Crazyflie"
    assert ep.handle(packet(crtp.LINK, 0, b"ping!")) == [packet(crtp.LINK, 0, b"ping!")]
    port, ch, data = one(ep.handle(packet(crtp.PLATFORM, 1, b"\0")))
    assert (port, ch, data[0], data[1]) == (13, 1, 0, 12)
    assert ep.handle(b"\xff") and ep.handle(b"") == []     # scan probe answered, empty ignored


def test_param_toc_read_write(ep, fleet):
    _, _, info = one(ep.handle(packet(crtp.PARAM, 0, b"\x03")))
    count, crc = struct.unpack("<HI", info[1:7])
    assert count == len(PARAMS) and crc == crtp.PARAM_CRC
    names = {}
    for k in range(count):
        _, _, item = one(ep.handle(packet(crtp.PARAM, 0, struct.pack("<BH", 2, k))))
        ident, type_byte = struct.unpack("<HB", item[1:4])
        group, name, _ = item[4:].split(b"\0")
        names[f"{group.decode()}.{name.decode()}"] = (ident, type_byte)
    for want in ("flightmode.stabModeRoll", "flightmode.stabModePitch", "flightmode.stabModeYaw",
                 "stabilizer.estimator", "stabilizer.controller", "commander.enHighLevel"):
        assert want in names
    ident, type_byte = names["flightmode.stabModeRoll"]
    assert type_byte == 0x08                                 # uint8, read-write
    assert names["supervisor.armingReq"][1] & 0x40           # read-only flag
    _, ch, data = one(ep.handle(packet(crtp.PARAM, 2, struct.pack("<HB", ident, 0))))
    assert ch == 2 and data == struct.pack("<HB", ident, 0)
    assert fleet.get_param(0, "flightmode.stabModeRoll") == 0
    assert fleet.get_param(1, "flightmode.stabModeRoll") == 1   # the other drone untouched
    _, ch, data = one(ep.handle(packet(crtp.PARAM, 1, struct.pack("<H", ident))))
    assert ch == 1 and data == struct.pack("<HBB", ident, 0, 0)
    _, _, data = one(ep.handle(packet(crtp.PARAM, 1, struct.pack("<H", 999))))
    assert data[2] == errno.ENOENT
    ro = names["supervisor.armingReq"][0]
    assert ep.handle(packet(crtp.PARAM, 2, struct.pack("<HB", ro, 0))) == []   # RO: ignored
    assert fleet.get_param(0, "supervisor.armingReq") == 1


def test_param_set_by_name(ep, fleet):
    msg = b"\0flightmode\0stabModePitch\0" + bytes([0x08, 0])
    _, ch, data = one(ep.handle(packet(crtp.PARAM, 3, msg)))
    assert ch == 3 and data[-1] == 0 and fleet.get_param(0, "flightmode.stabModePitch") == 0
    _, _, data = one(ep.handle(packet(crtp.PARAM, 3, b"\0no\0such\0" + bytes([0x08, 1]))))
    assert data[-1] == errno.ENOENT


def test_log_toc_blocks_and_data(ep, fleet):
    _, _, info = one(ep.handle(packet(crtp.LOG, 0, b"\x03")))
    count, crc = struct.unpack("<HI", info[1:7])
    assert count == len(LOG_VARS) and crc == crtp.LOG_CRC
    ids = {n: k for k, (n, _) in enumerate(LOG_VARS)}
    ops = struct.pack("<BH", 0x07, ids["stateEstimate.z"]) + struct.pack("<BH", 0x07, ids["pm.vbat"])
    _, ch, data = one(ep.handle(packet(crtp.LOG, 1, bytes([6, 1]) + ops)))
    assert ch == 1 and data == bytes([6, 1, 0])
    assert one(ep.handle(packet(crtp.LOG, 1, bytes([6, 1]) + ops)))[2][2] == errno.EEXIST
    big = b"".join(struct.pack("<BH", 0x07, ids["stateEstimate.x"]) for _ in range(7))
    assert one(ep.handle(packet(crtp.LOG, 1, bytes([6, 2]) + big)))[2][2] == errno.E2BIG
    assert one(ep.handle(packet(crtp.LOG, 1, bytes([3, 9, 5]))))[2][2] == errno.ENOENT
    assert one(ep.handle(packet(crtp.LOG, 1, bytes([3, 1, 2]))))[2] == bytes([3, 1, 0])   # start, 20 ms
    fleet.advance(0.05)
    out = [d for d in ep.due_packets() if d[0] >> 4 == crtp.LOG]
    assert len(out) == 1 and out[0][0] & 3 == 2
    body = out[0][1:]
    assert body[0] == 1
    stamp = body[1] | body[2] << 8 | body[3] << 16
    assert stamp == int(round(fleet.time * 1000))
    z, vbat = struct.unpack("<ff", body[4:])
    # the estimator (Lighthouse deck by default): within millimetres of the truth; the battery model
    assert z == pytest.approx(fleet.state(0)["pos"][2], abs=0.005)
    assert vbat == pytest.approx(fleet.log_values(0)["pm.vbat"], abs=1e-5) and 3.9 < vbat < 4.2
    assert [d for d in ep.due_packets() if d[0] >> 4 == crtp.LOG] == []     # not due again yet
    fleet.advance(0.02)
    assert len([d for d in ep.due_packets() if d[0] >> 4 == crtp.LOG]) == 1
    assert one(ep.handle(packet(crtp.LOG, 1, bytes([5]))))[2] == bytes([5, 0, 0])      # reset
    assert ep.blocks == {}


def test_mem_count_and_supervisor(ep, fleet):
    assert one(ep.handle(packet(crtp.MEM, 0, b"\x01")))[2] == bytes([1, 3])     # trajectory, tester, deck memory
    _, ch, data = one(ep.handle(packet(crtp.SUPERVISOR, 1, bytes([1, 1]))))
    assert ch == 1 and data == bytes([0x81, 1, 1]) and fleet.status(0)["armed"]
    _, ch, data = one(ep.handle(packet(crtp.SUPERVISOR, 0, bytes([0x0C]))))
    bits = struct.unpack("<H", data[1:3])[0]
    assert ch == 0 and data[0] == 0x8C and bits & 2 and bits == fleet.supervisor_bitfield(0)
    assert ep.handle(packet(crtp.SUPERVISOR, 1, bytes([3]))) == []
    assert fleet.status(0)["emergency_stopped"]


def test_legacy_arming_and_localization_estop(ep, fleet):
    _, ch, data = one(ep.handle(packet(crtp.PLATFORM, 0, bytes([1, 1]))))
    assert ch == 0 and data == bytes([1, 1, 1])
    ep.handle(packet(crtp.LOCALIZATION, 1, bytes([3])))
    assert fleet.status(0)["emergency_reason"] == "localization emergency stop"


def test_setpoint_and_stop_packets(ep, fleet):
    ep.handle(packet(crtp.COMMANDER, 0, struct.pack("<fffH", 1.0, 2.0, 3.0, 0)))
    assert fleet.status(0)["setpoints_received"] == 1 and not fleet.status(0)["locked"]
    ep.handle(packet(crtp.COMMANDER, 0, b"\x01\x02"))                      # short: ignored
    assert fleet.status(0)["setpoints_received"] == 1
    ep.handle(packet(crtp.GENERIC_COMMANDER, 0, b"\x00"))                   # STOP
    assert fleet.status(0)["setpoints_received"] == 2
    warn = ep.handle(packet(crtp.GENERIC_COMMANDER, 0, b"\x03" + bytes(16)))   # CPPM emulation: not emulated
    assert warn and all(p[0] >> 4 == crtp.CONSOLE for p in warn)
    assert b"not emulated" in b"".join(p[1:] for p in warn)
    assert fleet.status(0)["setpoints_received"] == 2
    warn = ep.handle(packet(crtp.GENERIC_COMMANDER, 0, b"\x07" + bytes(3)))     # position, too short
    assert b"bad length" in b"".join(p[1:] for p in warn) and fleet.status(0)["setpoints_received"] == 2


def test_generic_setpoint_types_decode_as_the_firmware():
    """Units and signs of each generic setpoint type (crtp_commander_generic.c) as cflib packs them."""
    sp = crtp.decode_generic(7, struct.pack("<ffff", 1.0, -2.0, 0.5, 90.0))            # position, yaw deg
    assert (sp.mode_x, sp.mode_y, sp.mode_z, sp.mode_yaw) == (ABS,) * 4
    assert list(sp.position) == [1.0, -2.0, 0.5] and sp.attitude[2] == pytest.approx(math.pi / 2)
    new, old = (crtp.decode_generic(t, struct.pack("<ffff", 0.3, 0.0, -0.1, s * 45.0)) for t, s in ((8, 1), (1, -1)))
    for sp in (new, old):                       # cflib negates the yaw rate for the legacy type only
        assert (sp.mode_x, sp.mode_z, sp.mode_yaw) == (VELOCITY, VELOCITY, VELOCITY) and not sp.velocity_body
        assert sp.velocity[0] == pytest.approx(0.3) and sp.rates[2] == pytest.approx(math.radians(45.0))
    hover = crtp.decode_generic(10, struct.pack("<ffff", 0.2, 0.1, 0.0, 0.4))
    assert hover.velocity_body and hover.mode_x == VELOCITY and hover.mode_z == ABS and hover.position[2] == pytest.approx(0.4)
    zd = crtp.decode_generic(9, struct.pack("<ffff", 5.0, 10.0, 0.0, 0.7))
    assert zd.mode_roll == ABS and zd.attitude[1] == pytest.approx(-math.radians(10.0)) and zd.position[2] == pytest.approx(0.7)
    man = crtp.decode_generic(11, struct.pack("<fffHB", 10.0, -20.0, 5.0, 30000, 1))   # rate mode
    assert man.mode_roll == VELOCITY and man.rates[1] == pytest.approx(math.radians(20.0)) and man.thrust == 30000
    assert crtp.decode_generic(6, bytes(28)) is None and crtp.decode_generic(3, bytes(10)) is None


def test_high_level_packets_decode_as_cflib_packs_them():
    assert crtp.decode_high_level(struct.pack("<BBff?f", 7, 3, 1.0, 0.5, False, 2.0)) == (
        "takeoff", 3, {"height": 1.0, "yaw": 0.5, "duration": 2.0})
    assert crtp.decode_high_level(struct.pack("<BBff?f", 8, 0, 0.0, 0.0, True, 3.0))[2]["yaw"] is None
    cmd, mask, args = crtp.decode_high_level(struct.pack("<BBBBfffff", 12, 0, 1, 1, 1.0, 2.0, 0.5, 0.0, 4.0))
    assert cmd == "go_to" and args["relative"] and args["linear"] and args["duration"] == 4.0
    assert crtp.decode_high_level(struct.pack("<BBBfffff", 4, 0, 0, 1.0, 2.0, 0.5, 0.0, 4.0))[2]["x"] == 1.0
    assert crtp.decode_high_level(struct.pack("<BB", 3, 0)) == ("stop", 0, {})
    assert crtp.decode_high_level(struct.pack("<BBBBBf", 5, 2, 1, 1, 7, 0.5)) == ("start_trajectory", 2, {
        "trajectory_id": 7, "timescale": 0.5, "relative_position": True, "relative_yaw": False, "reversed": True})
    assert crtp.decode_high_level(struct.pack("<BBBBBBf", 13, 0, 0, 1, 0, 3, 1.0))[2]["relative_yaw"]
    assert crtp.decode_high_level(struct.pack("<BBBBIB", 6, 4, 1, 1, 264, 5)) == ("define_trajectory", 0, {
        "trajectory_id": 4, "location": 1, "kind": 1, "offset": 264, "n_pieces": 5})
    cmd, mask, args = crtp.decode_high_level(struct.pack("<BBBBfffff", 11, 1, 0, 1, 3.0, 0.5, 0.2, 0.1, 4.0))
    assert cmd == "spiral" and mask == 1 and args["clockwise"] and not args["sideways"] and args["rf"] == pytest.approx(0.2)
    assert crtp.decode_high_level(struct.pack("<BBfBff", 9, 0, 1.0, 0, 0.0, 0.5)) is None      # with velocity


def test_non_finite_setpoints_are_dropped(ep, fleet):
    warn = ep.handle(packet(crtp.COMMANDER, 0, struct.pack("<fffH", float("nan"), 0.0, 0.0, 0)))
    assert b"NaN" in b"".join(p[1:] for p in warn)
    assert fleet.status(0)["setpoints_received"] == 0 and fleet.status(0)["locked"]
    with pytest.raises(ValueError):
        fleet.handle_setpoint(0, 0.0, float("inf"), 0.0, 0)


def test_garbage_never_raises(ep):
    rng = random.Random(1)
    for _ in range(3000):
        data = bytes(rng.randrange(256) for _ in range(rng.randrange(0, 32)))
        for reply in ep.handle(data):
            assert 1 <= len(reply) <= 31
    assert ep.rx == 3000
