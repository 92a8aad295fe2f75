"""The pure safety check (cfrace.flight.safety.check) and the flight config."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest

from cfrace.errors import ConfigError
from cfrace.flight.safety import check as sf
from cfrace.flight.config import FlightConfig, SafetyConfig, make_config
from cfrace.track import load_track

CFG = SafetyConfig()
DT = 0.01


@pytest.fixture(scope="module")
def fence():
    return sf.Fence.from_track(load_track("lemniscate"), CFG.geofence_margin_m)


def drone(**kw) -> sf.DroneInputs:
    base = dict(pos=np.array([0.0, 5.0, 1.0]), vel=np.array([2.0, 0.0, 0.0]), rot=np.eye(3), est_valid=True,
                est_age_s=0.0, obs=np.zeros(42, np.float32), action=np.zeros(4, np.float32), link_connected=True,
                link_rx_age_s=0.05, gate_crash=False)
    base.update(kw)
    return sf.DroneInputs(**base)


def inputs(d0=None, d1=None, **kw) -> sf.SafetyInputs:
    base = dict(t=5.0, dt=DT, tick_late_s=0.0001, drones=(d0 or drone(), d1 or drone()), operator_kill=None)
    base.update(kw)
    return sf.SafetyInputs(**base)


def rot_x(angle_deg: float) -> np.ndarray:
    a = math.radians(angle_deg)
    return np.array([[1, 0, 0], [0, math.cos(a), -math.sin(a)], [0, math.sin(a), math.cos(a)]])


def kinds(decision):
    return sorted((v.kind, v.drone, v.action) for v in decision.violations)


def test_nominal_flight_is_ok(fence):
    d = sf.check(inputs(), fence, CFG)
    assert d.ok and d.violations == () and d.stop == (False, False)


def test_fence_is_the_arena_grown_by_the_margin(fence):
    # lemniscate arena x [-2.5, 2.5], y [2, 9], z <= 3
    assert fence.lo[:2] == (-2.8, 1.7) and fence.hi == (2.8, 9.3, 3.3)
    assert fence.contains([2.79, 5.0, 1.0]) and not fence.contains([2.81, 5.0, 1.0])
    assert fence.contains([0.0, 1.71, 0.0]) and not fence.contains([0.0, 5.0, 3.31])


@pytest.mark.parametrize("change, kind", [
    (dict(pos=np.array([3.0, 5.0, 1.0])), "geofence"),
    (dict(pos=np.array([0.0, 5.0, 3.5])), "geofence"),
    (dict(pos=np.array([0.0, 5.0, 0.05])), "floor"),
    (dict(rot=rot_x(85.0)), "tilt"),
    (dict(rot=rot_x(180.0)), "tilt"),
    (dict(vel=np.array([10.0, 8.0, 0.0])), "speed"),
    (dict(est_age_s=0.2), "mocap_stale"),
    (dict(est_valid=False), "mocap_stale"),
    (dict(pos=np.array([np.nan, 5.0, 1.0])), "non_finite"),
    (dict(vel=np.array([np.inf, 0.0, 0.0])), "non_finite"),
    (dict(obs=np.r_[np.zeros(41), np.nan].astype(np.float32)), "non_finite"),
    (dict(action=np.array([0.1, np.nan, 0, 0], np.float32)), "non_finite"),
    (dict(link_connected=False), "link_lost"),
    (dict(link_rx_age_s=0.6), "link_lost"),
    (dict(gate_crash=True), "gate_crash"),
])
def test_one_drone_events_stop_only_that_drone(fence, change, kind):
    for i in (0, 1):
        ds = [drone(), drone()]
        ds[i] = drone(**change)
        d = sf.check(inputs(*ds), fence, CFG)
        assert (kind, i, sf.STOP_DRONE) in kinds(d)
        assert d.stop[i] and not d.stop[1 - i] and not d.stop_all


def test_limits_are_limits_not_off_by_one(fence):
    ok = [drone(rot=rot_x(79.0)), drone(vel=np.array([0.0, 11.9, 0.0]))]
    assert sf.check(inputs(*ok), fence, CFG).ok
    assert sf.check(inputs(drone(est_age_s=0.15), drone(link_rx_age_s=0.5)), fence, CFG).stop == (False, False)


def test_floor_rule_waits_for_take_off(fence):
    on_floor = drone(pos=np.array([1.3, 2.0, 0.02]), vel=np.zeros(3))
    assert sf.check(inputs(on_floor, drone(), t=0.5), fence, CFG).ok
    assert sf.check(inputs(on_floor, drone(), t=1.01), fence, CFG).stop == (True, False)


def test_short_dropout_rides_through_and_is_reported(fence):
    d = sf.check(inputs(drone(est_age_s=0.06)), fence, CFG)
    assert d.stop == (False, False)
    assert kinds(d) == [("mocap_dropout", 0, sf.NONE)]


def test_operator_kill_and_overrun_stop_everything(fence):
    d = sf.check(inputs(operator_kill="SIGTERM"), fence, CFG)
    assert d.stop_all and d.stop == (True, True) and kinds(d) == [("operator_kill", None, sf.STOP_ALL)]
    d = sf.check(inputs(tick_late_s=0.15), fence, CFG)
    assert d.stop_all and kinds(d) == [("loop_overrun", None, sf.STOP_ALL)]
    d = sf.check(inputs(tick_late_s=float("nan")), fence, CFG)
    assert d.stop_all


def test_missed_ticks_below_the_limit_are_reported_not_stopped(fence):
    d = sf.check(inputs(tick_late_s=0.05), fence, CFG)
    assert not d.stop_all and d.stop == (False, False)
    assert kinds(d) == [("tick_skipped", None, sf.NONE)]
    assert "5 tick(s) skipped" in d.violations[0].detail


def test_check_is_pure(fence):
    d0 = drone(pos=np.array([3.0, 5.0, 1.0]), action=np.array([np.nan, 0, 0, 0], np.float32))
    inp = inputs(d0, drone(est_age_s=0.3), tick_late_s=0.02)
    before = [x.copy() for x in (d0.pos, d0.action)]
    a, b = sf.check(inp, fence, CFG), sf.check(inp, fence, CFG)
    assert a == b
    assert all(np.array_equal(x, y, equal_nan=True) for x, y in zip(before, (d0.pos, d0.action)))
    assert kinds(a) == sorted([("geofence", 0, sf.STOP_DRONE), ("non_finite", 0, sf.STOP_DRONE),
                               ("mocap_stale", 1, sf.STOP_DRONE), ("tick_skipped", None, sf.NONE)])


def test_config_limits_are_used(fence):
    strict = replace(CFG, speed_max_mps=1.0, tilt_max_deg=10.0)
    d = sf.check(inputs(drone(rot=rot_x(20.0))), fence, strict)
    assert ("tilt", 0, sf.STOP_DRONE) in kinds(d) and ("speed", 0, sf.STOP_DRONE) in kinds(d)


def test_safety_config_validation():
    with pytest.raises(ConfigError, match="speed_max_mps"):
        SafetyConfig(speed_max_mps=-1.0)
    with pytest.raises(ConfigError, match="tilt_max_deg"):
        SafetyConfig(tilt_max_deg=200.0)


def test_flight_config_checks():
    with pytest.raises(ConfigError, match="bodies"):
        FlightConfig(track="lemniscate", ego="a", opp="b", bodies=("cf1",))
    with pytest.raises(ConfigError, match="own URI"):
        FlightConfig(track="lemniscate", ego="a", opp="b", uris=("udp://x:1", "udp://x:1"))
    with pytest.raises(ConfigError, match="missing --track"):
        make_config(None, ego="a", opp="b")
    assert FlightConfig(track="lemniscate", ego="a", opp="b").prewarm_s == 0.003
    assert FlightConfig(track="lemniscate", ego="a", opp="b").velocity_alpha == 1.0
    for bad in (0.0, 1.5, float("nan")):
        with pytest.raises(ConfigError, match="velocity_alpha"):
            FlightConfig(track="lemniscate", ego="a", opp="b", velocity_alpha=bad)
    for bad in (-0.001, 0.01, float("nan")):   # negative, a whole period (100 Hz), NaN
        with pytest.raises(ConfigError, match="prewarm_s"):
            FlightConfig(track="lemniscate", ego="a", opp="b", prewarm_s=bad)
    # mocap latency compensation: none for the in-process sim, 10 ms for everything else
    assert FlightConfig(track="lemniscate", ego="a", opp="b", mocap="sim").latency_comp == 0.0
    assert FlightConfig(track="lemniscate", ego="a", opp="b", mocap="vicon://10.0.0.1").latency_comp == 0.010
    assert FlightConfig(track="lemniscate", ego="a", opp="b", mocap="sim", latency_comp_s=0.004).latency_comp == 0.004
    for bad in (-0.001, 0.1, float("nan")):
        with pytest.raises(ConfigError, match="latency_comp_s"):
            FlightConfig(track="lemniscate", ego="a", opp="b", latency_comp_s=bad)


def test_flight_config_file(tmp_path):
    f = tmp_path / "room.yaml"
    f.write_text("uris: [radio://0/80/2M/E7E7E7E7E1, radio://1/90/2M/E7E7E7E7E2]\nbodies: [a, b]\n"
                 "mocap: vicon://10.0.0.1\nsafety: {geofence_margin_m: 0.5, speed_max_mps: 6}\n")
    cfg = make_config(f, track="lemniscate", ego="ours", opp="ds", bodies=None, safety_overrides={"tilt_max_deg": 60.0})
    assert cfg.uris[1].startswith("radio://1/") and cfg.bodies == ("a", "b") and cfg.mocap == "vicon://10.0.0.1"
    assert (cfg.safety.geofence_margin_m, cfg.safety.speed_max_mps, cfg.safety.tilt_max_deg) == (0.5, 6.0, 60.0)
    cfg = make_config(f, track="lemniscate", ego="ours", opp="ds", bodies=("x", "y"))
    assert cfg.bodies == ("x", "y")   # the command line wins
    f.write_text("prewarm_s: 0.002\nvelocity_alpha: 0.5\nlatency_comp_s: 0.006\n")
    assert make_config(f, track="lemniscate", ego="ours", opp="ds").latency_comp == 0.006
    assert make_config(f, track="lemniscate", ego="ours", opp="ds").prewarm_s == 0.002
    assert make_config(f, track="lemniscate", ego="ours", opp="ds").velocity_alpha == 0.5
    assert make_config(f, track="lemniscate", ego="ours", opp="ds", prewarm_s=0.0).prewarm_s == 0.0
    f.write_text("uris: [a, b]\nspeed_limit: 3\n")
    with pytest.raises(ConfigError, match="speed_limit.*unknown key"):
        make_config(f, track="lemniscate", ego="ours", opp="ds")
    f.write_text("safety: {speed_max: 3}\n")
    with pytest.raises(ConfigError, match="safety.speed_max.*unknown key"):
        make_config(f, track="lemniscate", ego="ours", opp="ds")


@pytest.mark.parametrize("change, kind", [
    (dict(pos=np.array([2.6, 5.0, 1.0])), "fence_near"),          # 0.2 m from the fence (x 2.8)
    (dict(pos=np.array([0.0, 5.0, 3.1])), "fence_near"),          # 0.2 m below the fence's ceiling
    (dict(mocap_glitches=3), "mocap_degraded"),
    (dict(blocked="opp down at (0.00, 5.50, 0.02)"), "opponent_down"),
    (dict(vbat=3.2, vbat_low_s=1.0), "low_battery"),
])
def test_soft_failsafes_land_only_that_drone(fence, change, kind):
    for i in (0, 1):
        ds = [drone(), drone()]
        ds[i] = drone(**change)
        d = sf.check(inputs(*ds), fence, CFG)
        assert kinds(d) == [(kind, i, sf.LAND_DRONE)]
        assert d.land[i] and not d.land[1 - i] and d.stop == (False, False)
        # a landing drone is past the soft rules (and the racing ones: floor, gate crash)
        landing = drone(**change, landing=True, gate_crash=True)
        assert sf.check(inputs(landing), fence, CFG).ok


def test_soft_limits_are_limits_and_hard_rules_win(fence):
    calm = [drone(pos=np.array([2.49, 5.0, 1.0])), drone(mocap_glitches=2), drone(vbat=3.2, vbat_low_s=0.9),
            drone(vbat=3.31, vbat_low_s=5.0)]
    for d in calm:
        assert sf.check(inputs(d), fence, CFG).ok
    both = sf.check(inputs(drone(mocap_glitches=5, rot=rot_x(85.0))), fence, CFG)
    assert both.stop[0] and not both.land[0]                     # a tumble cuts the motors, even when landing
    assert sf.check(inputs(drone(landing=True, rot=rot_x(85.0))), fence, CFG).stop[0]
    assert sf.check(inputs(drone(pos=np.array([3.0, 5.0, 1.0]))), fence, CFG).stop[0]   # outside: geofence, cut


def test_operator_land_lands_everyone_operator_kill_cuts(fence):
    d = sf.check(inputs(operator_land="SIGUSR1"), fence, CFG)
    assert d.land == (True, True) and not any(d.stop) and ("operator_land", None, sf.LAND_ALL) in kinds(d)
    d = sf.check(inputs(operator_land="SIGUSR1", operator_kill="SIGINT"), fence, CFG)
    assert d.stop_all and d.land == (False, False)
