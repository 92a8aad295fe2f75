"""The flight stack with N drones: lockstep and real-time dry-runs of 4 and 8 simulated drones,
faults of one drone and of all, batched inference of repeated policies, the CLI's policy lists."""

from __future__ import annotations

import numpy as np
import pytest

from cfrace.errors import ConfigError
from cfrace.flight.config import FlightConfig, drone_names
from cfrace.rehearsal.hold_policy import make_hold_policy

from test_flight_faults import PROFILE, check_landings, checked_dry_run, pols  # noqa: F401  (pols: a fixture)


def run(pols, tmp_path, n, faults=None, *, lockstep=True, timeout_s=2.5, track="lemniscate"):
    specs = tuple(pols["ego"] if i % 2 == 0 else pols["opp"] for i in range(n))
    cfg = FlightConfig(track=track, ego=specs[0], opp=specs[1], policies=specs, profile=PROFILE, quiet=True,
                       timeout_s=timeout_s, log=tmp_path / "f.mcap")
    return checked_dry_run(cfg, faults, lockstep)


def test_four_drones_lockstep_fly_the_whole_race_from_the_grid(pols, tmp_path):
    result, data = run(pols, tmp_path, 4)
    assert result["end"] == "timeout" and [d["name"] for d in result["drones"]] == ["d1", "d2", "d3", "d4"]
    assert all(d["stop_kind"] in ("timeout", "landed") for d in result["drones"])   # landed at the end
    assert set(check_landings(result).values()) <= {"race_end"}
    assert not any(e["action"] != "none" for e in result["safety_events"])
    # every drone streamed setpoints every tick, in the air (hold controller: hovers where it took off)
    setpoints = [m for _, m in data.messages("/setpoint")]
    assert len(setpoints) >= 240 and all(len(m) == 4 for m in setpoints)
    z = np.array([[m[f"cf{i + 1}"]["pos"][2] for i in range(4)] for _, m in data.messages("/estimate")])
    assert z[200:240].min() > 0.3                                  # in the air before the race's end
    # the start grid: two rows of two, 0.4 m apart
    p0 = np.array([[m[f"cf{i + 1}"]["pos"][:2] for i in range(4)] for _, m in data.messages("/estimate")][0])
    d = np.linalg.norm(p0[:, None] - p0[None], axis=-1) + np.eye(4) * 9
    assert d.min() == pytest.approx(0.4, abs=0.02)
    # repeated policies ran in one call: d1 and d3 (the same file) infer on the same ticks
    obs = [m for _, m in data.messages("/obs")]
    assert obs and all(("cf1" in m) == ("cf3" in m) and ("cf2" in m) == ("cf4" in m) for m in obs)
    # the 4-drone log replays bit for bit (opponent rule, batched calls and phases included)
    from cfrace.rehearsal.replay import replay_log

    rep = replay_log(tmp_path / "f.mcap")
    assert rep["identical"] and rep["observations"] > 400, rep


@pytest.mark.parametrize("fault, kind, stopped, end", [
    ("link_loss@1.0:d3", "link_lost", {"d3"}, "timeout"),             # one drone's fault stops only that drone
    ("geofence@1.0:d2", "geofence", {"d2"}, "timeout"),
    ("sigterm@1.0", "operator_kill", {"d1", "d2", "d3", "d4"}, "operator_kill"),   # the operator stops them all
    ("stall_200ms@1.0", "loop_overrun", {"d1", "d2", "d3", "d4"}, "loop_overrun"),
])
def test_faults_with_four_drones(pols, tmp_path, fault, kind, stopped, end):
    result, data = run(pols, tmp_path, 4, fault)
    assert result["end"] == end
    landed = check_landings(result)
    by_fault = {d["name"] for d in result["drones"] if d["stop_kind"] == kind or landed.get(d["name"]) == kind}
    assert by_fault == stopped, result["drones"]
    stops = {m["drone"] for _, m in data.messages("/event") if m.get("kind") == "stop"}
    assert stopped <= stops


def test_eight_drones_lockstep(pols, tmp_path):
    """Eight fit the complex track's start grid, not the lemniscate's (its back row would stand behind
    the arena's wall, inside the fence's soft limit): refused there before anything is sent."""
    d = tmp_path / "complex"
    d.mkdir()
    cpx = {"ego": str(make_hold_policy(d / "ego.onnx", "race42", "complex", False)),
           "opp": str(make_hold_policy(d / "opp.onnx", "solo36", "complex", False))}
    result, _ = run(cpx, tmp_path, 8, timeout_s=1.5, track="complex")
    assert result["end"] == "timeout" and len(result["drones"]) == 8
    assert result["loop"]["skipped"] == 0
    assert not any(e["action"] != "none" for e in result["safety_events"])   # every drone in the fence
    with pytest.raises(ConfigError, match="8 drones do not fit the lemniscate track's start grid"):
        run(pols, tmp_path, 8, timeout_s=1.5)


@pytest.mark.slow
def test_four_drones_real_time_through_cflib(pols, tmp_path):
    """The real cflib client over UDP to 4 simulated Crazyflies at 100 Hz."""
    result, _ = run(pols, tmp_path, 4, lockstep=False, timeout_s=2.0)
    assert result["end"] == "timeout" and len(result["drones"]) == 4
    assert result["loop"]["ticks"] + result["loop"]["skipped"] >= 195


def test_batched_inference_equals_one_call_per_drone(pols):
    from cfrace.policy import OnnxPolicy

    pol = OnnxPolicy(pols["ego"])
    obs = np.random.default_rng(0).normal(size=(4, 42)).astype(np.float32)
    one = np.concatenate([pol(o[None]) for o in obs])
    assert np.allclose(pol(obs), one, atol=1e-6)


def test_config_and_cli_lists():
    from cfrace.cli.flight import race_policies
    from cfrace.flight.loop.state import inference_phases

    assert drone_names(2) == ("ego", "opp") and drone_names(3) == ("d1", "d2", "d3")
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", policies=("ours", "ds", "ours"))
    assert cfg.bodies == ("cf1", "cf2", "cf3") and cfg.names == ("d1", "d2", "d3")
    with pytest.raises(ConfigError, match="need 3 URIs"):
        FlightConfig(track="lemniscate", ego="ours", opp="ds", policies=("ours", "ds", "ours"), uris=("udp://a:1",))
    assert race_policies("ours", "ds", None, None) == ("ours", "ds")
    assert race_policies(None, None, "ours,ds,ss", None) == ("ours", "ds", "ss")
    assert race_policies(None, None, "ours", 4) == ("ours",) * 4
    assert race_policies("ds", None, None, 3) == ("ds",) * 3
    for args, msg in (((None, None, "ours,ds", 3), "--drones 3 but 2"), (("ours", "ds", "ss", None), "not both"),
                      ((None, None, None, None), "give --ego"), (("ours", "ds", None, 4), "--policies P1")):
        with pytest.raises(ConfigError, match=msg):
            race_policies(*args)
    a, b = object(), object()
    assert inference_phases([a, b]) == [0, 1] and inference_phases([a, a, b, b]) == [0, 0, 1, 1]


def test_separation_rule(pols, tmp_path):
    from cfrace.flight.safety import check as sf
    from cfrace.flight.config import SafetyConfig

    assert sf.too_close({"a": [0, 0, 0], "b": [0.1, 0, 0], "c": [1, 0, 0], "d": [np.nan, 0, 0]}, 0.2) == \
        [("a", "b", 0.1)]
    result, _ = run(pols, tmp_path, 4, timeout_s=1.0)
    assert result["separation_at_stop"] == []   # 0.4 m grid, hovering apart: nobody too close
    # drones placed closer than the rule allows: refused before any link is touched
    specs = (pols["ego"], pols["opp"]) * 2
    cfg = FlightConfig(track="lemniscate", ego=specs[0], opp=specs[1], policies=specs, profile=PROFILE, quiet=True,
                       timeout_s=1.0, safety=SafetyConfig(min_separation_m=0.5))
    with pytest.raises(ConfigError, match="too close to take off.*cf1-cf2 0.40 m"):
        dry_run_plain(cfg)


@pytest.mark.parametrize("moved, why", [
    ({1: (0.5, 0.0, 0.0)}, r"cf2 stands at \(2\.20, 2\.50\) heading 90 deg, 0\.50 m from its slot \(1\.70, 2\.50\)"),
    ({0: (0.0, 0.0, 0.6)}, r"cf1 stands at \(1\.30, 2\.50\) heading 124 deg, 0\.00 m from its slot"),  # turned
])
def test_a_ground_start_off_the_grid_is_refused_before_anything_is_sent(pols, moved, why):
    """A second race with the drones where the first left them (`sim serve` does not put them back):
    refused with one line, no setpoint sent; the same drones on the grid fly."""
    import math

    from cfrace.flight.config import SafetyConfig
    from cfrace.rehearsal.dryrun import sim_race
    from cfrace.flight.setup import resolve_race
    from cfrace.simcf.firmware import SimFleet

    cfg = FlightConfig(track="lemniscate", ego=pols["ego"], opp=pols["opp"], profile=PROFILE, quiet=True,
                       timeout_s=0.3)
    setup = resolve_race(cfg)
    fleet = SimFleet(setup.track, setup.profile, 2, obstacles=False, decks=())
    start = fleet.state(0)["pos"], fleet.state(1)["pos"]
    for i, (dx, dy, dyaw) in moved.items():
        yaw = fleet._start_yaw + dyaw
        fleet.teleport(i, start[i] + (dx, dy, 0.0), quat=(math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)))
    with pytest.raises(ConfigError, match="not on the start grid for a ground start: " + why):
        sim_race(setup, fleet)
    assert all(fleet.status(i)["thrust"] == 0.0 and not fleet.status(i)["armed"] for i in range(2))
    # the rule can be switched off (safety.start_slot_m: 0)
    from dataclasses import replace
    assert sim_race(replace(setup, cfg=replace(cfg, safety=SafetyConfig(start_slot_m=0.0))), fleet).end == "timeout"


def dry_run_plain(cfg):
    from cfrace.rehearsal.dryrun import dry_run

    return dry_run(cfg, lockstep=True)


def test_fly_refuses_a_fifth_drone_on_one_radio_before_opening_anything(monkeypatch):
    from cfrace.flight import setup as fs

    opened = []
    monkeypatch.setattr(fs, "link_factory", lambda *a, **k: opened.append(a) or (lambda i, u: None))
    uris = tuple(f"radio://0/80/2M/E7E7E7E7E{i}" for i in range(1, 6))
    cfg = FlightConfig(track="lemniscate", ego="ours", opp="ds", policies=("ours", "ds") * 2 + ("ours",), uris=uris,
                       mocap="vicon://127.0.0.1")
    with pytest.raises(ConfigError, match="Crazyradio 0 carries 5 drones"):
        fs.real_io(cfg)
    assert not opened
    ok = replace_uris(cfg, uris[:4] + ("radio://1/80/2M/E7E7E7E7E5",))
    fs.real_io(ok)
    assert len(opened) == 1


def replace_uris(cfg, uris):
    from dataclasses import replace

    return replace(cfg, uris=uris)


@pytest.mark.parametrize("layout_name", ["race42", "race45_obstacles", "solo36", "solo39_obstacles"])
def test_the_drones_of_one_policy_are_observed_in_one_call_bit_for_bit(layout_name):
    """ObservationBuilder.many (the tick's one call per policy) gives each drone the observation the
    one-drone form gives it, bit for bit, for every layout."""
    import types

    from scipy.spatial.transform import Rotation

    from cfrace.contract.observations import LAYOUTS
    from cfrace.flight.loop.state import ObservationBuilder
    from cfrace.track import load_track

    corners = load_track("complex").gate_corners()
    builder, layout, rng = ObservationBuilder(corners), LAYOUTS[layout_name], np.random.default_rng(3)

    def est():
        return types.SimpleNamespace(pos=rng.normal(0.0, 3.0, 3), vel=rng.normal(0.0, 5.0, 3),
                                     rot=Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix())

    for m in (1, 2, 4, 8):
        ests, opps = [est() for _ in range(m)], [est() for _ in range(m)]
        targets = [int(t) for t in rng.integers(0, len(corners), m)]
        many = builder.many(layout, ests, targets, opps)
        assert many.shape == (m, layout.dim) and many.dtype == np.float32
        for j in range(m):
            assert np.array_equal(many[j], builder(layout, ests[j], targets[j], opps[j]))
