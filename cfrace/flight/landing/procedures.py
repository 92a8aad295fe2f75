"""Flights outside the race loop, on the firmware's own controllers (the high-level commander, the
drone's estimator fed with its mocap pose): the hover start before a race (``--start hover``) and
the first-flight hover test (``cfrace fly --hover``).

Each procedure streams every drone's mocap pose to it every ``dt`` while it runs (the firmware's
estimator needs it), reads poses with ``poses()`` -> {body: (pos (3,), quat (4,) wxyz)} and lets
time pass with ``wait(dt)`` (time.sleep for real drones, the simulator's advance in lockstep).
Links must be set up (armed); the set-up's zero-thrust unlock is a low-level setpoint, whose
priority blocks the high-level commander, so each procedure first hands control to it (notify-stop).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cfrace.flight.link.opener import check_link
from cfrace.errors import FlightError
from cfrace.flight.landing.descent import Touchdown
from cfrace.flight.landing.spots import LandingConfig
from cfrace.track import ground_start_positions


@dataclass(frozen=True)
class HoverConfig:
    takeoff_mps: float = 0.5       #: mean climb speed of the take-off
    move_mps: float = 0.5          #: mean speed of the go-to to the start position
    tolerance_m: float = 0.1       #: the drone holds within this of its target ...
    hold_s: float = 1.0            #: ... for this long before the race starts
    timeout_s: float = 10.0        #: after the go-to's planned end: give up (FlightError)
    dt: float = 0.01


def hover_start_positions(track, drones: int, height: float | None = None) -> tuple[np.ndarray, float]:
    """(drones, 3) hover positions and the yaw (rad) for ``--start hover``: above the ground-start
    grid (side by side, spawn.ground_distance before gate 0, facing it) at gate 0's height (or
    ``height``)."""
    pos, yaw = ground_start_positions(track, drones)
    pos[:, 2] = track.gates[0][2] if height is None else height
    return pos, yaw


def _stream(links, bodies, poses) -> dict:
    got = poses()
    for link, body in zip(links, bodies):
        if body in got:
            link.send_pose(*got[body])
    return got


def _fly_until(links, bodies, poses, wait, seconds: float, dt: float, done=None) -> dict:
    """Stream poses every dt for ``seconds`` or until done(poses) is true; -> the last poses."""
    got = _stream(links, bodies, poses)
    for _ in range(max(1, round(seconds / dt))):
        if done is not None and done(got):
            break
        wait(dt)
        got = _stream(links, bodies, poses)
    return got


def hover_start(links, bodies, poses, wait, targets, yaw: float, cfg: HoverConfig = HoverConfig()) -> dict:
    """Take every drone off and bring it to its target (N, 3) with the high-level commander, then
    hold until all have been within ``tolerance_m`` for ``hold_s``. Returns {"hold_error_m": per drone
    max distance from its target over the hold, "t_s": the procedure's duration}. FlightError (after
    landing every drone where it is) when they do not settle within ``timeout_s``."""
    targets = np.asarray(targets, np.float64)
    got = _stream(links, bodies, poses)
    start = np.array([got[b][0] for b in bodies], np.float64)
    climb = max(1.0, float(np.max(targets[:, 2] - start[:, 2])) / cfg.takeoff_mps)
    move = max(1.0, float(np.max(np.linalg.norm(targets[:, :2] - start[:, :2], axis=1))) / cfg.move_mps)
    for link, target in zip(links, targets):
        link.notify_stop()
        link.high_level("takeoff", height=float(target[2]), yaw=yaw, duration=climb)
    elapsed = climb
    _fly_until(links, bodies, poses, wait, climb, cfg.dt)
    for link, target in zip(links, targets):
        link.high_level("go_to", x=float(target[0]), y=float(target[1]), z=float(target[2]), yaw=yaw, duration=move)
    _fly_until(links, bodies, poses, wait, move, cfg.dt)
    elapsed += move

    def errors(got):
        return np.array([np.linalg.norm(np.asarray(got[b][0]) - t) if b in got else np.inf
                         for b, t in zip(bodies, targets)])
    worst, held, t_wait = np.zeros(len(bodies)), 0.0, 0.0
    while held < cfg.hold_s:
        if t_wait > cfg.timeout_s:
            land_in_place(links, bodies, poses, wait)
            raise FlightError(f"hover start: the drones did not settle within {cfg.tolerance_m} m of their start "
                              f"positions (errors {np.round(errors(got), 3).tolist()} m); landed")
        got = _fly_until(links, bodies, poses, wait, cfg.dt, cfg.dt)
        err = errors(got)
        t_wait += cfg.dt
        if np.all(err <= cfg.tolerance_m):
            held += cfg.dt
            worst = np.maximum(worst, err)
        else:
            held, worst = 0.0, np.zeros(len(bodies))
    return {"hold_error_m": [round(float(e), 4) for e in worst], "t_s": round(elapsed + t_wait, 2)}


def land_in_place(links, bodies, poses, wait, cfg: LandingConfig = LandingConfig(), ground_z: float = 0.0,
                  dt: float = 0.01) -> list[dict]:
    """Land every drone straight down where it is (high-level commander), stream poses until it
    is down, then stop it. Returns each drone's touchdown (Touchdown.as_dict)."""
    got = _stream(links, bodies, poses)
    heights = [float(got[b][0][2]) if b in got else 1.0 for b in bodies]
    duration = max(cfg.descent_s, max(heights) / 0.25)
    for link in links:
        link.high_level("land", height=cfg.land_height_m, yaw=None, duration=duration)
    touch = [Touchdown(ground_z) for _ in bodies]
    last = {b: np.asarray(got[b][0], np.float64) for b in bodies if b in got}
    t = 0.0
    for _ in range(round((duration + 0.5) / dt)):
        wait(dt)
        t += dt
        got = _stream(links, bodies, poses)
        for td, b in zip(touch, bodies):
            if b in got:
                pos = np.asarray(got[b][0], np.float64)
                vel = (pos - last[b]) / dt if b in last else np.zeros(3)   # finite differences of the poses
                last[b] = pos
                td.update(t, pos, vel)
    for link in links:
        link.stop()
    return [td.as_dict() for td in touch]


def hover_test(link, body: str, poses, wait, height: float = 0.5, hold_s: float = 5.0, ground_z: float = 0.0,
               dt: float = 0.01) -> dict:
    """A drone's first flight: take off to ``height`` above where it stands, hold ``hold_s``, land
    where it took off. Returns {"hold_error_m": max distance from the hover point while holding,
    "touchdown": {...}}."""
    got = _stream([link], [body], poses)
    if body not in got:
        raise FlightError(f"hover test: mocap body {body!r} not seen")
    p0 = np.asarray(got[body][0], np.float64)
    q = got[body][1]
    yaw = math.atan2(2.0 * (q[0] * q[3] + q[1] * q[2]), 1.0 - 2.0 * (q[2] ** 2 + q[3] ** 2))
    target = p0 + np.array([0.0, 0.0, height])
    link.notify_stop()
    climb = max(1.0, height / HoverConfig.takeoff_mps)
    link.high_level("takeoff", height=float(target[2]), yaw=yaw, duration=climb)
    _fly_until([link], [body], poses, wait, climb + 1.0, dt)
    worst = 0.0
    for _ in range(round(hold_s / dt)):
        got = _fly_until([link], [body], poses, wait, dt, dt)
        if body in got:
            worst = max(worst, float(np.linalg.norm(np.asarray(got[body][0]) - target)))
    touchdown = land_in_place([link], [body], poses, wait, ground_z=ground_z, dt=dt)[0]
    return {"hold_error_m": round(worst, 4), "touchdown": touchdown}


def mocap_poses(mocap):
    """A poses() function over an opened mocap source: the newest pose of every body seen so far."""
    latest: dict = {}

    def poses() -> dict:
        frame = mocap.read(0.0)
        if frame is not None:
            latest.update({b: (p.pos, p.quat) for b, p in frame.poses.items()})
        return latest
    return poses


def first_flight(setup, io, *, check: bool, hover_drones=()) -> dict:
    """`cfrace fly --check` / `--hover`: open the mocap and the links of ``io`` (a RaceIO), run the
    pre-flight checks (cfrace.flight.safety.preflight) and/or the hover test of each drone in
    ``hover_drones`` (only if the checks, when asked for, passed), and always stop and close
    everything. -> {"ok", "lines", "checks", "hover"}."""
    import time

    from cfrace.flight.safety.preflight import run_checks
    cfg = setup.cfg
    wait = io.wait or time.sleep
    mocap = io.open_mocap()
    links: list = []
    report = {"ok": True, "lines": [], "checks": [], "hover": []}
    try:
        mocap.open(cfg.mocap_timeout_s)
        poses = mocap_poses(mocap)
        poses()
        for i, uri in enumerate(io.uris):
            links.append(check_link(io.open_link(i, uri), uri))
            links[-1].connect(cfg.connect_timeout_s)
        if check:
            checks = run_checks(links, list(cfg.bodies), setup.profile, poses, wait)
            report["checks"] = [c.__dict__ for c in checks]
            report["lines"] += [c.line() for c in checks]
            report["ok"] = all(c.ok for c in checks)
        for i in hover_drones if report["ok"] else ():
            links[i].setup()
            res = hover_test(links[i], cfg.bodies[i], poses, wait, ground_z=setup.profile.collision_box[2] / 2.0)
            td = res["touchdown"]
            ok = res["hold_error_m"] <= HoverConfig.tolerance_m and td["t"] is not None and abs(td["vz_mps"]) <= 0.5
            report["hover"].append({"drone": i, **res, "ok": ok})
            report["lines"].append(f"{'ok  ' if ok else 'FAIL'} drone {i} hover: held within {res['hold_error_m']:.3f} m, "
                                   f"touchdown {td['vz_mps']} m/s at {td['place']}")
            report["ok"] &= ok
    finally:
        for link in links:
            try:
                link.stop()
                link.close()
            except Exception:  # noqa: BLE001 - every link must be closed
                pass
        mocap.close()
    return report
