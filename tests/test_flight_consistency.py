"""The pose/command consistency check (cfrace.flight.mocap.consistency, running sums over its window)
against the window's sums written out plainly here, on random histories of several drones that
start and stop being judged, and on a NaN that passes through the window."""

from __future__ import annotations

import math
import types

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from cfrace.drone import GRAVITY
from cfrace.flight.mocap import consistency as cs
from cfrace.flight.landing.descent import BRAKE


def _reference(hist: list, w: int, lag: int, dt: float, m: float):
    """(rate residual deg/s, dv residual m/s, limit m/s) of one drone's history, oldest first:
    entries (z, vel, rot, rates rad/s, thrust N), exactly window + lag + 1 of them."""
    airborne = min(h[0] for h in hist) >= cs.AIRBORNE_Z_M
    last, first = hist[-1], hist[-1 - w]
    rel = first[2].T @ last[2]
    rotvec = Rotation.from_matrix(rel).as_rotvec()
    cmd = sum(np.asarray(hist[-1 - lag - j][3]) for j in range(w)) / w
    rate = math.degrees(float(np.linalg.norm(rotvec / (w * dt) - cmd))) if airborne else 0.0
    exp, impulse = np.zeros(3), 0.0
    for j in range(w):
        a = hist[-1 - j - lag][4] / m
        exp += (hist[-1 - j][2][:, 2] * a - np.array([0.0, 0.0, GRAVITY])) * dt
        impulse += a * dt
    d = last[1] - first[1] - exp
    dv = float(np.linalg.norm(d)) if airborne else max(0.0, -float(d[2]))
    return rate, dv, cs.DV_LIMIT_MPS + cs.DV_LIMIT_REL * impulse


def _drone(rng, judged: bool, landing: bool = False):
    d = types.SimpleNamespace(stopped=False, action=np.zeros(4) if judged else None, landing=None,
                              rates_dps=tuple(rng.normal(0.0, 200.0, 3)), thrust_n=float(rng.uniform(0.0, 0.6)))
    if landing:
        d.landing, d.action = types.SimpleNamespace(phase=BRAKE), None
    return d


def _est(rng, valid: bool = True):
    return types.SimpleNamespace(pos=np.array([0.0, 0.0, rng.uniform(0.15, 2.0)]), vel=rng.normal(0.0, 3.0, 3),
                                 rot=Rotation.random(random_state=int(rng.integers(1 << 30))).as_matrix(),
                                 valid=valid)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_residuals_match_the_plain_per_drone_sums(seed):
    rng = np.random.default_rng(seed)
    n, dt, mass = 5, 0.01, 0.034
    mon = cs.ConsistencyMonitor(n, dt, mass)
    size = mon.window + mon.lag + 1
    hists: list[list] = [[] for _ in range(n)]
    checked = 0
    for _ in range(120):
        judged = rng.random(n) > 0.05            # now and then a drone is not judged: its history restarts
        drones = [_drone(rng, bool(j), landing=(i == 3)) for i, j in enumerate(judged)]
        ests = [_est(rng, valid=bool(rng.random() > 0.02)) for _ in range(n)]
        mon.update_all(drones, ests)
        for i, (d, e) in enumerate(zip(drones, ests)):
            ok = (d.action is not None or d.landing is not None) and e.valid
            if not ok:
                hists[i].clear()
                continue
            hists[i].append((float(e.pos[2]), e.vel.copy(), e.rot.copy(), np.radians(d.rates_dps), d.thrust_n))
            del hists[i][:-size]
        for i in range(n):
            if len(hists[i]) == size:
                ref = _reference(hists[i], mon.window, mon.lag, dt, mass)
                np.testing.assert_allclose(mon.residuals(i), ref, rtol=1e-9, atol=1e-7)
                checked += 1
            else:
                assert mon.residuals(i) is None and mon.over[i] == 0
    assert checked > 200


def test_a_mismatch_is_reported_after_mismatch_ticks_and_clears():
    """Poses that turn while the commands say hover: the drone's detail comes on the
    MISMATCH_TICKS-th tick over the limit, never for the drone whose poses fit its commands."""
    dt, mass = 0.01, 0.034
    mon = cs.ConsistencyMonitor(2, dt, mass)
    hover = mass * GRAVITY
    rng = np.random.default_rng(0)
    first = None
    for k in range(40):
        spin = Rotation.from_rotvec([0.0, 0.0, math.radians(600.0) * k * dt]).as_matrix()
        drones = [types.SimpleNamespace(stopped=False, action=np.zeros(4), landing=None, rates_dps=(0.0, 0.0, 0.0),
                                        thrust_n=hover) for _ in range(2)]
        ests = [types.SimpleNamespace(pos=np.array([0.0, 0.0, 1.0]), vel=np.zeros(3), rot=spin, valid=True),
                types.SimpleNamespace(pos=np.array([1.0, 0.0, 1.0]), vel=rng.normal(0.0, 1e-3, 3), rot=np.eye(3),
                                      valid=True)]
        out = mon.update_all(drones, ests)
        assert out[1] is None
        if out[0] is not None and first is None:
            first = k
            assert "body rates off by 600 deg/s" in out[0]
    size = mon.window + mon.lag + 1
    assert first == size - 1 + cs.MISMATCH_TICKS - 1
    assert mon.worst[0][0] == pytest.approx(600.0, rel=1e-6) and mon.worst[1][0] < 1e-6


def test_a_nan_that_left_the_window_leaves_no_trace():
    """A NaN command makes the residuals NaN while it is in the window, and exact again after."""
    rng = np.random.default_rng(5)
    dt, mass = 0.01, 0.034
    mon = cs.ConsistencyMonitor(1, dt, mass)
    size = mon.window + mon.lag + 1
    hist: list = []
    for k in range(4 * size):
        d, e = _drone(rng, True), _est(rng)
        if k == size:
            d.rates_dps = (math.nan, 0.0, 0.0)
        mon.update_all([d], [e])
        hist.append((float(e.pos[2]), e.vel.copy(), e.rot.copy(), np.radians(d.rates_dps), d.thrust_n))
        del hist[:-size]
        if k >= 3 * size:
            np.testing.assert_allclose(mon.residuals(0), _reference(hist, mon.window, mon.lag, dt, mass),
                                       rtol=1e-9, atol=1e-7)
