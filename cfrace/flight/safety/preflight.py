"""Pre-flight checks (`cfrace fly --check`): what must hold before a drone is armed for a race.

1. **Firmware**: CRTP protocol version >= 12 (arming through the supervisor, the generic
   commander's current setpoint types; cflib needs it too).
2. **Battery**: pm.vbat at rest >= ``min_vbat``.
3. **Link**: round trip (cflib's ping, p95) <= ``max_latency_ms`` and the radio's ack rate >=
   ``min_link_quality`` where the link reports them.
4. **Which body is which drone, and its yaw**: each drone in turn makes a short signal, a hop of a
   few centimetres (rate setpoints: a thrust pulse, then a nose-down pitch pulse and back while in
   the air, then down and off). The mocap body that rises must be the drone's configured body, the
   others must stay still. The rotation of the nose-down pulse, seen in the mocap body's frame,
   must be about its +y axis: its direction gives the yaw offset between the mocap object's frame
   and the drone's (it must be within ``yaw_tolerance_deg``).

Checks 1-3 arm nothing; if one fails, no drone is armed. Each check is one line in the result.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.rotations import quat_to_rot

#: the signal: (duration s, roll rate, pitch rate, yaw rate deg/s, thrust in weights), then DESCENT
#: until every body is back within LANDED_M of its start height (at most DESCENT_MAX_S), then off
HOP = ((0.10, 0.0, 0.0, 0.0, 1.4), (0.08, 0.0, 120.0, 0.0, 1.0), (0.08, 0.0, -120.0, 0.0, 1.0),
       (0.25, 0.0, 0.0, 0.0, 0.8))
DESCENT = (0.0, 0.0, 0.0, 0.95)
DESCENT_MAX_S = 1.5
LANDED_M = 0.012
SETTLE_S = 0.3     #: s of recording after the motors are off


@dataclass(frozen=True)
class PreflightConfig:
    min_protocol: int = 12
    min_vbat: float = 3.8            #: V at rest
    max_latency_ms: float = 30.0
    min_link_quality: float = 90.0   #: %
    min_rise_m: float = 0.03         #: the signalling drone's body rises at least this
    still_m: float = 0.01            #: the other bodies move less than this
    yaw_tolerance_deg: float = 15.0


@dataclass
class Check:
    name: str        #: firmware, battery, link, body, yaw
    drone: int
    ok: bool
    detail: str

    def line(self) -> str:
        return f"{'ok  ' if self.ok else 'FAIL'} drone {self.drone} {self.name}: {self.detail}"


def yaw_offset_deg(quat_before, quat_tilted) -> float:
    """The yaw offset (deg) of the mocap body frame from the drone's, from a nose-down rotation of
    the drone (about its own +y): the rotation axis in the mocap body frame is (sin d, cos d, 0)."""
    rel = quat_to_rot(quat_before).T @ quat_to_rot(quat_tilted)          # rotation in the body frame
    axis = np.array([rel[2, 1] - rel[1, 2], rel[0, 2] - rel[2, 0], rel[1, 0] - rel[0, 1]])
    return math.degrees(math.atan2(axis[0], axis[1]))


def signal(link, profile, poses, wait, dt: float = 0.01) -> dict[str, list]:
    """Fly the HOP signal with ``link`` (already set up: armed, rate mode, unlocked), recording
    ``poses()`` ({body: (pos, quat)}) every dt; ``wait(dt)`` lets dt pass (time.sleep, or advancing
    a simulator). -> {body: [(pos, quat), ...]}. The link is stopped at the end, whatever happens."""
    traces: dict[str, list] = {}

    def record():
        for body, (pos, quat) in poses().items():
            traces.setdefault(body, []).append((np.asarray(pos, np.float64), np.asarray(quat, np.float64)))
    def counts(weights):
        return int(np.clip(profile.thrust_curve.to_counts(weights * profile.mass * GRAVITY), 1000, 60000))

    def down():
        return all(tr[-1][0][2] - tr[0][0][2] < LANDED_M for tr in traces.values())
    try:
        record()
        for duration, p, q, r, weights in HOP:
            for _ in range(max(1, round(duration / dt))):
                link.send(p, q, r, counts(weights))
                wait(dt)
                record()
        for _ in range(round(DESCENT_MAX_S / dt)):
            if down():
                break
            link.send(*DESCENT[:3], counts(DESCENT[3]))
            wait(dt)
            record()
    finally:
        link.stop()
    for _ in range(round(SETTLE_S / dt)):
        wait(dt)
        record()
    return traces


def judge_signal(traces: dict[str, list], body: str, drone: int, cfg: PreflightConfig) -> list[Check]:
    """The body and yaw checks of one drone's signal."""
    rise = {b: max(p[2] for p, _ in tr) - tr[0][0][2] for b, tr in traces.items()}
    moved = {b: max(float(np.linalg.norm(p - tr[0][0])) for p, _ in tr) for b, tr in traces.items()}
    if not rise:
        return [Check("body", drone, False, "no mocap body seen during the signal")]
    top = max(rise, key=rise.get)
    others = {b: m for b, m in moved.items() if b != body and m > cfg.still_m}
    ok = top == body and rise[body] >= cfg.min_rise_m and not others
    detail = (f"body {body!r} rose {100 * rise.get(body, 0.0):.1f} cm"
              + (f"; but {top!r} rose most ({100 * rise[top]:.1f} cm)" if top != body else "")
              + (f"; {', '.join(sorted(others))} moved too" if others else "")
              + ("; too little: is the drone profile (--profile) this drone's? its thrust may be too low"
                 if not ok and top == body and not others else ""))
    checks = [Check("body", drone, ok, detail)]
    if ok:
        tr = traces[body]
        tilt = [math.degrees(math.acos(max(-1.0, min(1.0, quat_to_rot(q)[2, 2])))) for _, q in tr]
        k = int(np.argmax(tilt))
        off = yaw_offset_deg(tr[0][1], tr[k][1])
        checks.append(Check("yaw", drone, abs(off) <= cfg.yaw_tolerance_deg and tilt[k] > 3.0,
                            f"mocap frame yawed {off:+.1f} deg from the drone's (tilt {tilt[k]:.0f} deg)"))
    return checks


def check_status(link, drone: int, cfg: PreflightConfig) -> list[Check]:
    """Firmware, battery and link checks of one connected link (nothing armed)."""
    st = link.read_status()
    q = link.quality
    vbat = st.get("vbat", float("nan"))
    lat, lq = q.latency_ms, q.link_quality
    # a Crazyradio measures the link quality; a UDP link (simulated drones) has none to report
    radio = str(getattr(link, "uri", "")).startswith("radio://")
    link_ok = (not lat == lat or lat <= cfg.max_latency_ms) and (lq >= cfg.min_link_quality if lq == lq else not radio)
    quality = f"{lq:.0f} %" if lq == lq else ("not reported (a radio must report it)" if radio else
                                              "not measured on this link")
    return [
        Check("firmware", drone, st["protocol"] >= cfg.min_protocol,
              f"CRTP protocol {st['protocol']} (need >= {cfg.min_protocol})"),
        Check("battery", drone, vbat == vbat and vbat >= cfg.min_vbat, f"{vbat:.2f} V (need >= {cfg.min_vbat} V)"),
        Check("link", drone, bool(q.connected and link_ok),
              f"latency {lat:.1f} ms, link quality {quality} (limits {cfg.max_latency_ms:g} ms, "
              f"{cfg.min_link_quality:g} %)"),
    ]


def run_checks(links, bodies, profile, poses, wait, cfg: PreflightConfig = PreflightConfig()) -> list[Check]:
    """Every check for connected ``links`` (mocap bodies ``bodies`` in the same order). The signals
    (which arm each drone in turn) only run when every status check passed."""
    checks = [c for i, link in enumerate(links) for c in check_status(link, i, cfg)]
    if not all(c.ok for c in checks):
        return checks
    for i, (link, body) in enumerate(zip(links, bodies)):
        link.setup()
        checks += judge_signal(signal(link, profile, poses, wait), body, i, cfg)
    return checks
