"""Motion capture: the frame and pose types, the MocapSource protocol and the base of the sources
(cfrace.flight.mocap.sources: real systems, replay and open_mocap; cfrace.flight.mocap.simulated: simulation)."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol, runtime_checkable

import numpy as np

from cfrace.errors import MocapError


@dataclass(frozen=True)
class Pose:
    pos: np.ndarray    #: (3,) m, world frame
    quat: np.ndarray   #: (4,) w, x, y, z; world from body


@dataclass(frozen=True)
class MocapFrame:
    t: float                  #: s, source clock (monotonic)
    poses: dict[str, Pose]    #: body name -> pose; occluded bodies absent
    seq: int                  #: frame counter of this source, from 1


@runtime_checkable
class MocapSource(Protocol):
    name: str

    def open(self, timeout_s: float = 5.0) -> None: ...
    def read(self, timeout_s: float = 0.02) -> MocapFrame | None: ...
    def close(self) -> None: ...
    def bodies_seen(self) -> set[str]: ...


def frame_to_msg(frame: MocapFrame) -> dict:
    """The /mocap/pose flight-log message of a frame (replay reads it back exactly)."""
    return {"t_src": frame.t, "seq": frame.seq,
            "poses": {b: {"pos": p.pos.tolist(), "quat": p.quat.tolist()}
                      for b, p in frame.poses.items()}}


def frame_from_msg(msg: dict) -> MocapFrame:
    """Inverse of frame_to_msg; ValueError saying what is wrong in a malformed message."""
    if not isinstance(msg, dict) or not isinstance(msg.get("poses"), dict):
        raise ValueError("a /mocap/pose message needs 'poses': {body: {pos, quat}}, got "
                         f"{type(msg.get('poses') if isinstance(msg, dict) else msg).__name__}")
    poses = {}
    for b, p in msg["poses"].items():
        if not isinstance(p, dict):
            raise ValueError(f"the pose of body {b!r} should be {{pos, quat}}, got {type(p).__name__}")
        pos, quat = np.asarray(p["pos"], dtype=np.float64), np.asarray(p["quat"], dtype=np.float64)
        if pos.shape != (3,) or quat.shape != (4,):
            raise ValueError(f"the pose of body {b!r} should have 3 pos and 4 quat numbers")
        poses[b] = Pose(pos, quat)
    return MocapFrame(t=float(msg["t_src"]), poses=poses, seq=int(msg["seq"]))


def finite_pose(pos, quat) -> Pose | None:
    p = np.asarray(pos, dtype=np.float64).reshape(3)
    q = np.asarray(quat, dtype=np.float64).reshape(4)
    # one finite check on a plain-float sum (finite iff every value is, at these magnitudes):
    # this runs for every body of every frame in the 100 Hz tick
    if not math.isfinite(sum(p.tolist()) + sum(q.tolist())):
        return None
    return Pose(p, q)


class SourceBase:
    """Shared parts: required-body check, bodies_seen, context manager."""

    name = ""

    def __init__(self, name: str, bodies: list[str]):
        self.name = name
        self.bodies = list(bodies)
        self._seen: set[str] = set()
        self._opened = False

    def bodies_seen(self) -> set[str]:
        return set(self._seen)

    def _missing(self) -> list[str]:
        return [b for b in self.bodies if b not in self._seen]

    def _body_error(self) -> MocapError:
        if not self._seen:    # nothing at all: the system is not reachable or tracks nothing, not a naming slip
            return MocapError(f"{self.name}: no poses at all (expected bodies {', '.join(self.bodies)}): is the "
                              "motion capture system running, reachable at that address and tracking them?")
        seen = ", ".join(sorted(self._seen))
        missing = self._missing()
        what = f"body '{missing[0]}'" if len(missing) == 1 else \
            "bodies " + ", ".join(f"'{b}'" for b in missing)
        return MocapError(f"unknown mocap {what} (seen: {seen}) from {self.name}")

    def close(self) -> None:
        self._opened = False

    def __enter__(self):
        self.open()
        return self

    def __exit__(self, *exc) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------
# real systems through libmotioncapture, in a worker process
