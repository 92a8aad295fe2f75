"""The tick's parts for more than two drones: who observes whom, and one inference call per policy.

OpponentPicker: a drone flying a multi-agent policy observes one opponent, the one its opponent
rule picks (its metadata's ``opponent_rule``, else cfrace.contract.observations.DEFAULT_OPPONENT_RULE)
from the estimates and the race progress, on the training's race line (choose_opponents,
polyline, track_position: one definition for training, evaluation and flight). Two drones: the
other one, as always (the tick does not ask).
due_groups / batched_step: the drones due on a tick, grouped by policy object (a policy named
several times is loaded once, cfrace.flight.setup.resolve_race), each group in ONE onnxruntime
call on the stacked observations.
"""

from __future__ import annotations

import math
import time

import numpy as np

from cfrace.contract.observations import DEFAULT_OPPONENT_RULE, choose_opponents, polyline, track_position
from cfrace.errors import ConfigError
from cfrace.flight.safety import check as sf
from cfrace.rotations import quat_to_rot
from cfrace.track import HEADING_JITTER_RAD, ground_start_positions


class OpponentPicker:
    """Index of the drone each drone observes, cached per list of estimates (one tick's)."""

    def __init__(self, drones: list, progress):
        self.drones, self.progress = drones, progress
        self.rules = [d.meta.get("opponent_rule", DEFAULT_OPPONENT_RULE) for d in drones]
        self._needed = {r for r, d in zip(self.rules, drones) if d.layout.opponent}
        self._gates = np.asarray(progress.gates, dtype=np.float64)
        self._cum, self._lap_len = polyline(self._gates)
        self._for: list | None = None
        self._picked: dict = {}

    def index(self, i: int, ests: list) -> int:
        """The drone that drone i observes, from these estimates."""
        if self._for is not ests:
            p = self.progress
            pos = np.nan_to_num(np.array([e.pos for e in ests], dtype=np.float64))
            # "nearest" needs no place on the race line (a fifth of an 8-drone tick otherwise)
            tpos = None if self._needed <= {"nearest"} else track_position(
                self._gates, self._cum, self._lap_len, np.asarray(p.start_gate), np.asarray(p.gates_passed),
                np.asarray(p.target), pos)
            alive = np.array([not d.stopped for d in self.drones])
            self._picked = {rule: choose_opponents(pos, tpos, alive, rule) for rule in self._needed}
            self._for = ests
        return int(self._picked[self.rules[i]][i])


def due_groups(drones: list, due: list[bool]) -> list[list[int]]:
    """The due drones' indices grouped by their policy object, in drone order."""
    groups: dict[int, list[int]] = {}
    for i, (d, yes) in enumerate(zip(drones, due)):
        if yes:
            groups.setdefault(id(d.policy), []).append(i)
    return list(groups.values())


def batched_step(core, group: list[int], ests: list) -> tuple[list[float], float]:
    """The policy step of the drones of one policy (one drone or several): their observations built in
    one call, ONE inference call on them, each drone's action through its action map (TickCore._act);
    returns (observation s per drone: the group's share, the call's s)."""
    t0 = time.perf_counter()
    obs = core.observe_group(group, ests)
    t1 = time.perf_counter()
    acts = np.asarray(core.drones[group[0]].policy(obs), dtype=np.float32).reshape(len(group), 4)
    infer = time.perf_counter() - t1
    for i, o, a in zip(group, obs, acts):
        core._act(i, o.copy(), a.copy())
    return [(t1 - t0) / len(group)] * len(group), infer


class _Unread:
    """A lockstep mocap source with one frame handed back: the loop's first read gets the source's
    newest frame, or this one when the source has nothing newer (it makes one per tick). Not for
    real time: there new frames keep coming and a handed-back one would be old (a stale pose)."""

    def __init__(self, source, frame):
        self.source, self.frame = source, frame

    def read(self, timeout_s: float = 0.02):
        if self.frame is None:
            return self.source.read(timeout_s)
        newer = self.source.read(0.0)
        out = newer if newer is not None else self.frame
        self.frame = None
        return out

    def close(self) -> None:
        self.source.close()


def off_start_slots(poses: dict, bodies, track, tol_m: float) -> list[str]:
    """One phrase per drone of ``bodies`` (in start-grid order) that does not stand on its ground
    start slot (cfrace.track.ground_start_positions): its mocap pose farther than ``tol_m`` from the
    slot (in the horizontal) or turned more than the training's heading jitter from facing gate 0."""
    slots, yaw = ground_start_positions(track, len(bodies))
    out = []
    for body, slot in zip(bodies, slots):
        pose = poses[body]
        rot = quat_to_rot(pose.quat)
        heading = math.atan2(rot[1, 0], rot[0, 0])
        turned = (heading - yaw + math.pi) % (2.0 * math.pi) - math.pi
        off = math.hypot(float(pose.pos[0]) - slot[0], float(pose.pos[1]) - slot[1])
        if off > tol_m or abs(turned) > HEADING_JITTER_RAD:
            out.append(f"{body} stands at ({pose.pos[0]:.2f}, {pose.pos[1]:.2f}) heading {math.degrees(heading):.0f} "
                       f"deg, {off:.2f} m from its slot ({slot[0]:.2f}, {slot[1]:.2f}) heading "
                       f"{math.degrees(yaw):.0f} deg")
    return out


def check_take_off(mocap, cfg, realtime: bool, track):
    """Take-off rules on the first frame that shows every body, before anything is sent
    (cfrace.flight.safety.check): every pair of cfg.bodies at least cfg.safety.min_separation_m apart,
    and on a ground start every drone on its start-grid slot (within cfg.safety.start_slot_m, facing
    gate 0), else ConfigError. Returns the mocap source to read from (a lockstep source gets the
    frame it made handed back)."""
    separation = len(cfg.bodies) >= 2 and cfg.safety.min_separation_m > 0
    slots = cfg.start == "ground" and cfg.safety.start_slot_m > 0
    if not (separation or slots):
        return mocap
    t_end = time.monotonic() + cfg.mocap_timeout_s
    while time.monotonic() < t_end:
        frame = mocap.read(0.05)
        if frame is not None and all(b in frame.poses for b in cfg.bodies):
            close = sf.too_close({b: frame.poses[b].pos for b in cfg.bodies}, cfg.safety.min_separation_m) \
                if separation else []
            if close:
                pairs = ", ".join(f"{a}-{b} {d:.2f} m" for a, b, d in close)
                raise ConfigError(f"drones too close to take off ({pairs}; at least "
                                  f"{cfg.safety.min_separation_m:g} m, safety.min_separation_m)")
            off = off_start_slots(frame.poses, cfg.bodies, track, cfg.safety.start_slot_m) if slots else []
            if off:
                served = " (drones of `cfrace sim serve`: restart it or serve them with --reset-after-flight)" \
                    if cfg.mocap.startswith("sim://") else ""
                raise ConfigError(f"not on the start grid for a ground start: {'; '.join(off)} (at most "
                                  f"{cfg.safety.start_slot_m:g} m, safety.start_slot_m): put each drone on its slot, "
                                  f"facing gate 0{served}")
            return mocap if realtime else _Unread(mocap, frame)
    return mocap
