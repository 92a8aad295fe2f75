"""Drone profiles: shipped calibrations, sources for every parameter, strict errors, thrust curve,
allocation matrix."""

from __future__ import annotations

import math

import numpy as np
import pytest
import yaml

from cfrace.drone import _PARAM_KEYS, DEFAULT_PROFILE, GRAVITY, load_profile
from cfrace.errors import ConfigError
from cfrace.paths import CALIBRATION_DIR

PROFILES = ("cf2x_paper", "cf21bl")


def raw(name="cf2x_paper"):
    return yaml.safe_load((CALIBRATION_DIR / f"{name}.yaml").read_text())


def load_mutated(tmp_path, mutate, name="cf2x_paper"):
    data = raw(name)
    mutate(data)
    path = tmp_path / "p.yaml"
    path.write_text(yaml.safe_dump(data))
    return load_profile(path), path


def expect_error(tmp_path, mutate, key, *words):
    path = tmp_path / "p.yaml"
    with pytest.raises(ConfigError) as info:
        load_mutated(tmp_path, mutate)
    msg = str(info.value)
    assert str(path) in msg and f"'{key}'" in msg and "\n" not in msg, msg
    for w in words:
        assert w in msg, msg


@pytest.mark.parametrize("name", PROFILES)
def test_shipped_profiles_load_and_every_parameter_has_a_source(name):
    p = load_profile(name)
    assert p.name == name and p.source.endswith(f"{name}.yaml")
    assert set(p.sources) == set(_PARAM_KEYS)
    assert all(isinstance(v, str) and v.strip() for v in p.sources.values())
    assert sorted(p.rotor_dirs) == [-1.0, -1.0, 1.0, 1.0]
    # the motors can lift the drone; the thrust curve ends at the real drone's saturated thrust, or
    # for the paper's simulation profile at the action map's full thrust T m g (the link then passes
    # every thrust the policy was trained to command; the simulated motors saturate as in training)
    assert p.max_collective_thrust > 1.5 * p.weight
    end = p.max_thrust_weights * p.weight if name == "cf2x_paper" else p.max_collective_thrust
    assert p.thrust_curve.newtons[-1] == pytest.approx(end, rel=0.02)


def test_default_profile_and_paper_values():
    p = load_profile()
    assert p.name == DEFAULT_PROFILE == "cf2x_paper"
    assert p.mass == 0.0282 and p.inertia == (1.6572e-5, 1.6656e-5, 2.9262e-5)
    assert p.max_collective_thrust == pytest.approx(0.575, abs=1e-9)  # 4 k_eta 2500^2
    assert p.max_collective_thrust / p.weight == pytest.approx(2.08, abs=0.01)
    np.testing.assert_allclose(p.max_rates, [math.radians(100), math.radians(100), math.radians(200)])
    assert p.collision_radius == pytest.approx(0.065)
    assert p.weight == pytest.approx(0.0282 * GRAVITY)


def test_missing_source_is_an_error(tmp_path):
    expect_error(tmp_path, lambda d: d["sources"].pop("k_eta"), "sources.k_eta", "source")
    expect_error(tmp_path, lambda d: d["sources"].__setitem__("mass", "  "), "sources.mass", "source")
    expect_error(tmp_path, lambda d: d.pop("sources"), "sources", "missing")


def test_unknown_keys_are_errors(tmp_path):
    expect_error(tmp_path, lambda d: d.update(masss=0.03), "masss", "unknown key")
    expect_error(tmp_path, lambda d: d["sources"].update(color="paint"), "sources.color", "unknown key")
    expect_error(tmp_path, lambda d: d["pid_yaw"].update(kf=1.0), "pid_yaw.kf", "unknown key")
    expect_error(tmp_path, lambda d: d["thrust_curve"].update(volts=[1, 2]), "thrust_curve.volts", "unknown key")


def test_bad_values_are_errors(tmp_path):
    expect_error(tmp_path, lambda d: d.__setitem__("inertia", [1e-5, 1e-5]), "inertia", "expected 3 numbers")
    expect_error(tmp_path, lambda d: d.__setitem__("mass", float("nan")), "mass", "finite")
    expect_error(tmp_path, lambda d: d.__setitem__("mass", -0.1), "mass", "> 0")
    expect_error(tmp_path, lambda d: d.__setitem__("rotor_dirs", [1, 1, 1, -1]), "rotor_dirs", "two +1")
    expect_error(tmp_path, lambda d: d.__setitem__("motor_speed", [100.0, 50.0]), "motor_speed", "min < max")


def test_non_increasing_thrust_curve_is_an_error(tmp_path):
    def flat_counts(d):
        d["thrust_curve"] = {"counts": [0, 10000, 10000], "newtons": [0.0, 0.1, 0.2]}

    def falling_newtons(d):
        d["thrust_curve"] = {"counts": [0, 10000, 20000], "newtons": [0.0, 0.2, 0.1]}

    expect_error(tmp_path, flat_counts, "thrust_curve", "strictly increasing")
    expect_error(tmp_path, falling_newtons, "thrust_curve", "strictly increasing")
    expect_error(tmp_path, lambda d: d.__setitem__("thrust_curve", {"counts": [0], "newtons": [0.0]}),
                 "thrust_curve", ">= 2 points")
    expect_error(tmp_path, lambda d: d["thrust_curve"].__setitem__("newtons", [0.0, 0.5]),
                 "thrust_curve.newtons", "expected 7 numbers")
    expect_error(tmp_path, lambda d: d["thrust_curve"]["counts"].__setitem__(-1, 70000), "thrust_curve.counts[6]",
                 "<= 65535")


def test_missing_file_and_invalid_yaml(tmp_path):
    with pytest.raises(ConfigError, match="no such drone profile") as info:
        load_profile("no_such_drone")
    assert "cf2x_paper" in str(info.value) and "cf21bl" in str(info.value)
    bad = tmp_path / "bad.yaml"
    bad.write_text("name: [unclosed\n")
    with pytest.raises(ConfigError, match="invalid YAML") as info:
        load_profile(bad)
    assert str(bad) in str(info.value)


@pytest.mark.parametrize("name", PROFILES)
def test_thrust_curve_round_trip(name):
    tc = load_profile(name).thrust_curve
    counts = np.linspace(0, tc.counts[-1], 257)
    newtons = tc.to_newtons(counts)
    assert np.all(np.diff(newtons) > 0)
    np.testing.assert_allclose(tc.to_counts(newtons), counts, atol=1e-6)
    newtons = np.linspace(0.0, tc.newtons[-1], 101)
    np.testing.assert_allclose(tc.to_newtons(tc.to_counts(newtons)), newtons, atol=1e-9)
    # hand-checked points of the cf2x_paper curve; clamped outside the curve's range
    if name == "cf2x_paper":
        assert tc.to_newtons(15000) == pytest.approx((0.0783 + 0.1834) / 2)
        assert tc.to_counts(0.4738) == pytest.approx(40000)
        assert tc.counts[-1] == 60000  # the firmware's cap on the port-3 thrust setpoint
    assert tc.to_counts(-1.0) == 0 and tc.to_counts(10.0) == tc.counts[-1]


@pytest.mark.parametrize("name", PROFILES)
def test_allocation_matrix_and_its_inverse(name):
    p = load_profile(name)
    a = p.allocation()
    assert a.shape == (4, 4)
    inv = np.linalg.inv(a)
    np.testing.assert_allclose(a @ inv, np.eye(4), atol=1e-9)
    # hover: equal rotor forces, no torque
    np.testing.assert_allclose(inv @ np.array([p.weight, 0, 0, 0]), [p.weight / 4] * 4, rtol=1e-12)
    # rotor layout r1 (+,+), r2 (+,-), r3 (-,-), r4 (-,+) at arm_length, 45 deg
    xy = p.rotor_xy
    np.testing.assert_allclose(np.linalg.norm(xy, axis=1), p.arm_length)
    np.testing.assert_array_equal(np.sign(xy), [[1, 1], [1, -1], [-1, -1], [-1, 1]])
    # a pure +roll torque lifts the +y rotors (1, 4) and lowers the -y ones (2, 3)
    f = inv @ np.array([p.weight, 1e-4, 0, 0])
    assert f[0] > f[1] and f[3] > f[2]
    # a pure +pitch torque lifts the -x rotors (3, 4)
    f = inv @ np.array([p.weight, 0, 1e-4, 0])
    assert f[2] > f[1] and f[3] > f[0]
    # yaw torque from the spin directions with k_m / k_eta
    np.testing.assert_allclose(a[3], (p.k_m / p.k_eta) * np.asarray(p.rotor_dirs))
