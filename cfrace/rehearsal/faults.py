"""Fault injection for `cfrace sim dry-run --faults ...`: real faults through the real stack.

A fault spec is ``KIND@T[:DRONE]``, comma separated, T in s of race time, DRONE ego (default) or
opp, e.g. ``mocap_dropout_short@3.0,link_loss@2.0:opp,sigterm@5``. Kinds:

    mocap_dropout_short  no mocap frame at all for 80 ms (below mocap_stale_s): ride through
    mocap_dropout_long   the drone's body missing from every frame for 1 s: stale -> stop it
    pose_outlier         one frame puts the drone's body 1 m off: the estimator must reject it
    geofence             from T the drone's policy output is replaced by a climb: level
                         attitude, GEOFENCE_CLIMB_MPS upwards (well below the speed limit), so
                         that it really leaves the fence through its ceiling and the geofence,
                         not the speed or tilt rule, must stop it
    nan_policy           from T the drone's policy outputs NaN
    link_loss            from T nothing gets through the drone's link either way (a UDP relay
                         drops every datagram; lockstep: the direct link goes silent)
    stall_50ms           the loop thread blocks for 50 ms once (missed ticks are skipped)
    stall_200ms          ... for 200 ms (beyond overrun_stop_s: stop all)
    sigterm / sigint     the process sends itself SIGTERM / SIGINT (the real signal handlers)
    swap_bodies          from T the two drones' mocap bodies are swapped (a labelling mistake):
                         each drone is steered on the other's poses; the consistency check
                         (poses must move with the commands) must stop them
    replay_poses         from T the mocap source replays the frames it gave REPLAY_BACK_S
                         earlier, in order (recorded poses): the consistency check must stop them

Soft failsafes (the drone lands, docs/flight.md "Safety"):

    mocap_glitchy        three pose outliers 0.3 s apart: degraded mocap (mocap_degraded)
    low_battery          the drone's battery is nearly empty from T (simulated drones only)
    operator_land        the process sends itself SIGUSR1, the operator's "land now" (every drone)
"""

from __future__ import annotations

import os
import selectors
import signal
import socket
import threading
from dataclasses import dataclass, replace

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.errors import ConfigError
from cfrace.flight.mocap.sources import MocapFrame, Pose

KINDS = ("mocap_dropout_short", "mocap_dropout_long", "pose_outlier", "geofence", "nan_policy", "link_loss",
         "stall_50ms", "stall_200ms", "sigterm", "sigint", "swap_bodies", "replay_poses", "mocap_glitchy",
         "low_battery", "operator_land")
REPLAY_BACK_S = 1.0      #: s, how far back the replay_poses fault replays
GLITCH_SPACING_S = 0.3
SHORT_DROPOUT_S = 0.08
LONG_DROPOUT_S = 1.0
OUTLIER_OFFSET = np.array([0.8, 0.0, 0.6])   #: m, 1 m off
GEOFENCE_CLIMB_MPS = 4.0     #: m/s, the geofence fault's climb
LEVEL_GAIN = 6.0             #: 1/s, body rate per rad of tilt of the geofence fault's levelling


@dataclass(frozen=True)
class Fault:
    kind: str
    t: float
    drone: str = "ego"


def parse_faults(text: str | None, names: tuple[str, ...] = ("ego", "opp")) -> list[Fault]:
    """Fault specs; DRONE one of ``names`` (the race's drone names: ego, opp or d1 .. dN), the first by default."""
    if not text:
        return []
    out = []
    for item in text.split(","):
        item = item.strip()
        if not item:
            continue
        kind, at, rest = item.partition("@")
        when, _, drone = rest.partition(":")
        if kind not in KINDS or not at:
            raise ConfigError(f"--faults: bad fault {item!r} (expected KIND@T[:ego|opp], KIND one of {', '.join(KINDS)})")
        try:
            t = float(when)
            if not t >= 0:
                raise ValueError
        except ValueError:
            raise ConfigError(f"--faults: bad time in {item!r} (seconds >= 0)") from None
        drone = drone or names[0]
        if drone not in names:
            raise ConfigError(f"--faults: bad drone in {item!r} ({' or '.join(names)})")
        out.append(Fault(kind, t, drone))
    return out


class FaultyMocap:
    """Wraps a MocapSource; drops or alters frames while a fault is active."""

    def __init__(self, source, injector: "FaultInjector"):
        self.source, self.inj = source, injector
        self.name = getattr(source, "name", "mocap")
        self.recorded: list = []     #: (t, poses) of the frames given, for replay_poses

    def open(self, timeout_s: float = 5.0) -> None:
        self.source.open(timeout_s)

    def close(self) -> None:
        self.source.close()

    def bodies_seen(self) -> set[str]:
        return self.source.bodies_seen()

    def read(self, timeout_s: float = 0.02) -> MocapFrame | None:
        frame = self.source.read(timeout_s)
        if frame is None:
            return None
        t = self.inj.t
        poses = dict(frame.poses)
        self.recorded.append((t, poses))
        for f in self.inj.faults:
            if f.kind == "replay_poses" and t >= f.t:
                back = [p for tt, p in self.recorded if tt <= t - REPLAY_BACK_S]
                poses = dict(back[-1]) if back else poses
            if f.kind == "swap_bodies" and t >= f.t:   # the fault's drone and the next one swap bodies
                names = list(self.inj.bodies)
                a = self.inj.bodies[f.drone]
                b = self.inj.bodies[names[(names.index(f.drone) + 1) % len(names)]]
                if a in poses and b in poses:
                    poses[a], poses[b] = poses[b], poses[a]
            body = self.inj.bodies[f.drone]
            if f.kind == "mocap_dropout_short" and f.t <= t < f.t + SHORT_DROPOUT_S:
                return None
            if f.kind == "mocap_dropout_long" and f.t <= t < f.t + LONG_DROPOUT_S:
                poses.pop(body, None)
            if f.kind in ("pose_outlier", "mocap_glitchy") and f in self.inj.pending_outliers and body in poses:
                self.inj.pending_outliers.discard(f)
                p = poses[body]
                poses[body] = Pose(p.pos + OUTLIER_OFFSET, p.quat)
        return replace(frame, poses=poses) if poses is not frame.poses else frame


class UdpCutRelay:
    """A UDP relay between cflib and one simulated drone that can be cut (link loss)."""

    def __init__(self, target_port: int, host: str = "127.0.0.1"):
        self.target = (host, int(target_port))
        self.front = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.front.bind((host, 0))
        self.back = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self.back.connect(self.target)
        self.port = self.front.getsockname()[1]
        self.uri = f"udp://{host}:{self.port}"
        self.is_cut = False
        self._client = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="udp-cut-relay", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        sel = selectors.DefaultSelector()
        sel.register(self.front, selectors.EVENT_READ, 0)
        sel.register(self.back, selectors.EVENT_READ, 1)
        while not self._stop.is_set():
            for key, _ in sel.select(timeout=0.1):
                try:
                    if key.data == 0:
                        data, self._client = self.front.recvfrom(512)
                        if not self.is_cut:
                            self.back.send(data)
                    else:
                        data = self.back.recv(512)
                        if not self.is_cut and self._client is not None:
                            self.front.sendto(data, self._client)
                except OSError:
                    pass
        sel.close()

    def cut(self) -> None:
        self.is_cut = True

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self.front.close()
        self.back.close()


class FaultInjector:
    """Triggers the faults at their times; hooks called by the loop (before_tick, filter_*)."""

    def __init__(self, faults: list[Fault], bodies: dict[str, str]):
        self.faults = list(faults)
        self.bodies = dict(bodies)                    # drone name -> mocap body
        self.t = 0.0
        self.fired: set[Fault] = set()
        self.pending_outliers: set[Fault] = set()
        self.first_glitch: dict[Fault, float] = {}    # mocap_glitchy: each glitch -> the first one's time
        self.cutters: dict[str, object] = {}          # drone name -> callable that cuts its link
        self.drainers: dict[str, object] = {}         # drone name -> callable that empties its battery (sim)
        self.log: list[dict] = []
        self.loop = None                              # the flight loop (before_tick)

    def wrap_mocap(self, source):
        return FaultyMocap(source, self) if self.faults else source

    def _fire(self, loop, f: Fault) -> None:
        self.fired.add(f)
        self.log.append({"t": round(self.t, 3), "kind": f.kind, "drone": f.drone})
        if loop.log is not None:
            loop.log.write("/event", self.t, {"kind": "fault", "fault": f.kind, "drone": f.drone,
                                              "text": f"injected fault {f.kind} on {f.drone}"})
        if f.kind in ("pose_outlier", "mocap_glitchy"):
            self.pending_outliers.add(f)
            if f.kind == "mocap_glitchy" and f.t < self.first_glitch.setdefault(f, f.t) + 2 * GLITCH_SPACING_S:
                self.faults.append(replace(f, t=f.t + GLITCH_SPACING_S))     # the next glitch
                self.first_glitch[self.faults[-1]] = self.first_glitch[f]
        elif f.kind == "low_battery":
            drain = self.drainers.get(f.drone)
            if drain is not None:
                drain()
        elif f.kind == "operator_land":
            os.kill(os.getpid(), signal.SIGUSR1)
        elif f.kind == "link_loss":
            cut = self.cutters.get(f.drone)
            if cut is not None:
                cut()
        elif f.kind.startswith("stall_"):
            loop.clock.stall(int(f.kind[len("stall_"):-2]) / 1000.0)
        elif f.kind in ("sigterm", "sigint"):
            os.kill(os.getpid(), signal.SIGTERM if f.kind == "sigterm" else signal.SIGINT)

    def before_tick(self, loop, t: float) -> None:
        self.t = t
        self.loop = loop
        for f in self.faults:
            if f not in self.fired and t >= f.t:
                self._fire(loop, f)

    def filter_obs(self, drone, obs: np.ndarray) -> np.ndarray:
        return obs

    def filter_action(self, drone, act: np.ndarray, t: float) -> np.ndarray:
        for f in self.faults:
            if f.drone == drone.name and f in self.fired:
                if f.kind == "nan_policy":
                    return np.full(4, np.nan, np.float32)
                if f.kind == "geofence":
                    return self.climb(drone)
        return act

    def climb(self, drone) -> np.ndarray:
        """The action that levels the drone and climbs at GEOFENCE_CLIMB_MPS (its estimate this tick)."""
        est = self.loop.core.last_ests[[d.name for d in self.loop.drones].index(drone.name)]
        rot = np.asarray(est.rot, np.float64)
        b3 = rot[:, 2]
        axis = np.cross(b3, [0.0, 0.0, 1.0])                   # world: turn b3 towards up
        rates = LEVEL_GAIN * (rot.T @ axis)                     # rad/s, body frame
        k = np.radians(drone.meta["max_rates_deg"])
        hover = drone.mass * GRAVITY / max(float(b3[2]), 0.5)
        thrust = hover * (1.0 + 0.5 * (GEOFENCE_CLIMB_MPS - float(est.vel[2])))
        a0 = 2.0 * thrust / drone.setpoint_map.scale - 1.0
        return np.clip(np.array([a0, *(rates / k)], np.float32), -1.0, 1.0)
