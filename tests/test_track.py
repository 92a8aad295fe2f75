"""Track loader: shipped tracks, gate geometry (corners, bars) and strict errors."""

from __future__ import annotations

import copy
import math

import numpy as np
import pytest
import yaml

from cfrace.errors import ConfigError
from cfrace.track import load_track

BASE = {
    "name": "unit",
    "gate": {"opening": 1.0, "border": 0.2, "thickness": 0.04},
    "gates": [[1.0, 2.0, 1.5, 0.0], [-1.0, 0.0, 1.0, math.pi / 2]],
    "obstacles": [{"center": [3.0, -3.0], "size": [0.2, 1.0, 2.0], "yaw": 0.3}],
    "arena": {"x": [-4.0, 4.0], "y": [-4.0, 4.0], "z_max": 3.0},
}


def write(tmp_path, data, name="t.yaml"):
    path = tmp_path / name
    path.write_text(yaml.safe_dump(data))
    return path


def load(tmp_path, mutate=None):
    data = copy.deepcopy(BASE)
    if mutate:
        mutate(data)
    return load_track(write(tmp_path, data))


def expect_error(tmp_path, mutate, key, *words):
    path = tmp_path / "t.yaml"
    with pytest.raises(ConfigError) as info:
        load(tmp_path, mutate)
    msg = str(info.value)
    assert str(path) in msg and f"'{key}'" in msg, msg
    assert "\n" not in msg
    for w in words:
        assert w in msg, msg
    return msg


# ------------------------------------------------------------------------------ shipped tracks

def test_shipped_tracks_load_with_the_paper_layout():
    ct, lt = load_track("complex"), load_track("lemniscate")
    assert (ct.name, ct.num_gates, len(ct.obstacles)) == ("complex", 6, 4)
    assert (lt.name, lt.num_gates, len(lt.obstacles)) == ("lemniscate", 6, 2)
    g = ct.gate_array()
    np.testing.assert_allclose(g[2, :3], [-2.0, -3.5, 2.0])  # split-S: gates 2 and 3 stacked
    np.testing.assert_allclose(g[3, :3], [-2.0, -3.5, 0.75])
    lg = lt.gate_array()
    np.testing.assert_allclose(lg[1], lg[4])  # lemniscate: gate 1 and 4 are the same gate
    assert ct.arena.x == (-6.0, 5.0) and lt.arena.y == (2.0, 9.0)
    assert ct.without_obstacles().obstacles == ()


def test_load_by_path_and_by_name_agree():
    by_name = load_track("lemniscate")
    by_path = load_track(by_name.source)
    assert by_name == by_path


# ------------------------------------------------------------------------------ geometry

def test_gate_corners_order_and_values_hand_computed(tmp_path):
    t = load(tmp_path)
    c = t.gate_corners()
    assert c.shape == (2, 4, 3)
    # yaw 0 at (1, 2, 1.5): gate y axis = world +y; order (0,+d,+d), (0,-d,+d), (0,-d,-d), (0,+d,-d)
    np.testing.assert_allclose(c[0], [[1.0, 2.5, 2.0], [1.0, 1.5, 2.0], [1.0, 1.5, 1.0], [1.0, 2.5, 1.0]], atol=1e-12)
    # yaw 90 deg at (-1, 0, 1): gate y axis = world -x
    np.testing.assert_allclose(c[1], [[-1.5, 0.0, 1.5], [-0.5, 0.0, 1.5], [-0.5, 0.0, 0.5], [-1.5, 0.0, 0.5]],
                               atol=1e-12)


def test_gate_corners_lie_in_the_gate_plane_of_shipped_tracks():
    for name in ("complex", "lemniscate"):
        t = load_track(name)
        g, c = t.gate_array(), t.gate_corners()
        n = np.stack([np.cos(g[:, 3]), np.sin(g[:, 3]), np.zeros(len(g))], -1)
        rel = c - g[:, None, :3]
        np.testing.assert_allclose(np.einsum("gcj,gj->gc", rel, n), 0.0, atol=1e-12)
        np.testing.assert_allclose(np.abs(rel[..., 2]), 0.5)  # +-d vertically


def _inside(points, centre, half, yaw):
    c, s = math.cos(yaw), math.sin(yaw)
    d = points - centre
    local = np.stack([c * d[:, 0] + s * d[:, 1], -s * d[:, 0] + c * d[:, 1], d[:, 2]], -1)
    return np.all(np.abs(local) <= half + 1e-9, axis=1)


def test_gate_bars_cover_the_frame_and_leave_the_opening_free(tmp_path):
    t = load(tmp_path)
    centres, halves, yaws = t.gate_bars()
    assert centres.shape == (8, 3) and halves.shape == (8, 3) and yaws.shape == (8,)
    # gate 0 (yaw 0 at (1, 2, 1.5)): top, bottom, left, right
    np.testing.assert_allclose(centres[:4], [[1, 2, 2.1], [1, 2, 0.9], [1, 2.6, 1.5], [1, 1.4, 1.5]], atol=1e-12)
    np.testing.assert_allclose(halves[0], [0.02, 0.7, 0.1])
    np.testing.assert_allclose(halves[2], [0.02, 0.1, 0.5])
    np.testing.assert_allclose(yaws, [0.0] * 4 + [math.pi / 2] * 4)
    rng = np.random.default_rng(0)
    for gi, (x, y, z, yaw) in enumerate(t.gate_array()):
        gy = np.array([-math.sin(yaw), math.cos(yaw), 0.0])
        uv = rng.uniform(-0.7, 0.7, size=(4000, 2))
        pts = np.array([x, y, z]) + uv[:, :1] * gy + uv[:, 1:] * np.array([0.0, 0.0, 1.0])
        hit = np.zeros(len(pts), bool)
        for k in range(4 * gi, 4 * gi + 4):
            hit |= _inside(pts, centres[k], halves[k], yaws[k])
        in_opening = np.all(np.abs(uv) < 0.5 - 1e-6, axis=1)
        in_frame = ~np.all(np.abs(uv) <= 0.5 + 1e-6, axis=1)
        assert not hit[in_opening].any(), "a bar blocks the opening"
        assert hit[in_frame].all(), "the bars leave a hole in the frame"


def test_obstacle_boxes_stand_on_the_floor(tmp_path):
    c, h, y = load(tmp_path).obstacle_boxes()
    np.testing.assert_allclose(c, [[3.0, -3.0, 1.0]])
    np.testing.assert_allclose(h, [[0.1, 0.5, 1.0]])
    np.testing.assert_allclose(y, [0.3])
    c, h, y = load(tmp_path, lambda d: d.pop("obstacles")).obstacle_boxes()
    assert c.shape == (0, 3) and h.shape == (0, 3) and y.shape == (0,)


# ------------------------------------------------------------------------------ strict errors

def test_unknown_key_is_an_error(tmp_path):
    expect_error(tmp_path, lambda d: d.update(gatez=[]), "gatez", "unknown key")
    expect_error(tmp_path, lambda d: d["arena"].update(z_min=0.0), "arena.z_min", "unknown key")
    expect_error(tmp_path, lambda d: d["obstacles"][0].update(colour="red"), "obstacles[0].colour", "unknown key")


def test_wrong_vector_length_is_an_error(tmp_path):
    expect_error(tmp_path, lambda d: d["gates"].__setitem__(1, [0.0, 0.0, 1.0]), "gates[1]", "expected 4 numbers")
    expect_error(tmp_path, lambda d: d["obstacles"][0].__setitem__("size", [1.0, 1.0]), "obstacles[0].size",
                 "expected 3")


def test_non_finite_and_non_numeric_values_are_errors(tmp_path):
    expect_error(tmp_path, lambda d: d["gates"][0].__setitem__(2, float("nan")), "gates[0][2]", "finite")
    expect_error(tmp_path, lambda d: d["arena"].__setitem__("z_max", float("inf")), "arena.z_max", "finite")
    expect_error(tmp_path, lambda d: d["gates"][0].__setitem__(0, "one"), "gates[0][0]", "expected a number")
    expect_error(tmp_path, lambda d: d["gate"].__setitem__("opening", -1.0), "gate.opening", "> 0")


def test_gate_outside_the_arena_is_an_error(tmp_path):
    expect_error(tmp_path, lambda d: d["gates"][0].__setitem__(0, 5.0), "gates[0]", "outside the arena")
    expect_error(tmp_path, lambda d: d["gates"][0].__setitem__(2, 2.5), "gates[0]", "ceiling")  # frame hits ceiling
    expect_error(tmp_path, lambda d: d["gates"][0].__setitem__(2, 0.5), "gates[0]", "floor")


def test_obstacle_through_a_gate_opening_is_an_error(tmp_path):
    wall = {"center": [1.0, 2.0], "size": [2.0, 0.1, 3.0], "yaw": 0.0}  # crosses gate 0's opening
    msg = expect_error(tmp_path, lambda d: d["obstacles"].append(wall), "obstacles[1]", "gate 0")
    assert "opening" in msg
    # the same wall just beside the frame is fine
    beside = dict(wall, center=[1.0, 3.0])
    assert len(load(tmp_path, lambda d: d["obstacles"].append(beside)).obstacles) == 2


def test_missing_file_and_invalid_yaml(tmp_path):
    missing = tmp_path / "nope.yaml"
    with pytest.raises(ConfigError, match="no such track file") as info:
        load_track(missing)
    assert str(missing) in str(info.value) and "lemniscate" in str(info.value)
    with pytest.raises(ConfigError, match="no such track file"):
        load_track("no_such_track_name")
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: x\ngates: [[1, 2, 3, 4]\narena: {x: [0, 1]}\n")
    with pytest.raises(ConfigError, match="invalid YAML") as info:
        load_track(bad)
    assert str(bad) in str(info.value) and "line" in str(info.value) and "\n" not in str(info.value)
    top = tmp_path / "list.yaml"
    top.write_text("- 1\n- 2\n")
    with pytest.raises(ConfigError, match="top level must be a mapping"):
        load_track(top)


def test_missing_required_keys_and_too_few_gates(tmp_path):
    expect_error(tmp_path, lambda d: d.pop("arena"), "arena", "missing")
    expect_error(tmp_path, lambda d: d.pop("gates"), "gates", "missing")
    expect_error(tmp_path, lambda d: d.__setitem__("gates", [[0.0, 0.0, 1.0, 0.0]]), "gates", "at least 2")
    expect_error(tmp_path, lambda d: d["arena"].__setitem__("x", [1.0, -1.0]), "arena", "low < high")


def test_thin_obstacle_through_a_gate_opening_is_an_error(tmp_path):
    thin = {"center": [1.0, 2.049], "size": [2.0, 0.04, 3.0], "yaw": 0.0}  # 4 cm wall, 4.9 cm off centre
    expect_error(tmp_path, lambda d: d["obstacles"].append(thin), "obstacles[1]", "gate 0")
