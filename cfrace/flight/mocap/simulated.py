"""Mocap sources of simulated drones: `sim` (an in-process simulator's .poses(), with noise,
latency and dropout) and `sim://HOST:PORT` (a SimCrazyflieServer's pose stream in another process)."""

from __future__ import annotations

import time

import numpy as np

from cfrace.errors import MocapError
from cfrace.flight.mocap.base import MocapFrame, SourceBase, finite_pose
from cfrace.loopmodel import interpolate_pose, perturb_pose

class SimSource(SourceBase):
    """Poses from a simulator's .poses() with Gaussian position noise, latency and body dropout:
    the lab-loop rules training uses (cfrace.loopmodel: interpolate_pose, perturb_pose)."""

    def __init__(self, sim, bodies: list[str], noise_m: float, latency_s: float, dropout: float,
                 seed: int):
        super().__init__("sim", bodies)
        self.sim, self.noise_m, self.latency_s, self.dropout = sim, noise_m, latency_s, dropout
        self._rng = np.random.default_rng(seed)
        self._buffer: list[tuple[float, dict]] = []   # (t, {body: (pos, quat)}) not yet delivered
        self._last_t: float | None = None
        self._delivered_t = -np.inf
        self._seq = 0

    def _get(self) -> tuple[float, dict] | None:
        """(t, {body: (pos, quat)}) from the simulator (None before its first pose); bodies seen."""
        try:
            got = self.sim.poses()
        except Exception as exc:   # noqa: BLE001 - a broken simulator is a mocap failure here
            raise MocapError(f"{self.name}: poses() failed: {type(exc).__name__}: {exc}") from None
        if got is None:            # nothing received yet (pose stream)
            return None
        self._seen.update(got[1])
        return float(got[0]), got[1]

    def _poll(self) -> float:
        got = self._get()
        if got is None:
            return -np.inf if self._last_t is None else self._last_t
        t, poses = got
        if self._last_t is None or t > self._last_t:
            self._buffer.append((t, {b: (np.array(p, dtype=np.float64), np.array(q, dtype=np.float64))
                                     for b, (p, q) in poses.items()}))
            self._last_t = t
        return t

    def _newest(self) -> tuple[float, dict] | None:
        """(t, {body: (pos, quat)}) of the simulator's poses if newer than any seen, else None."""
        got = self._get()
        if got is None:
            return None
        t, poses = got
        if self._last_t is not None and t <= self._last_t:
            return None
        self._last_t = t
        return t, poses

    def open(self, timeout_s: float = 5.0) -> None:
        if self._opened:
            return
        deadline = time.monotonic() + timeout_s
        self._poll()
        while self._missing() and time.monotonic() < deadline:
            time.sleep(0.005)
            self._poll()
        if self._missing():
            raise self._body_error()
        if self.latency_s > 0 and self._buffer:
            # a live system has been streaming before we connect: the scene as it was one latency
            # ago (the drones sit still before a flight) is already on its way
            t0, first = self._buffer[0]
            self._buffer.insert(0, (t0 - self.latency_s, first))
        self._opened = True

    def read(self, timeout_s: float = 0.02) -> MocapFrame | None:
        if not self._opened:
            self.open()
        if self.latency_s == 0.0 and not self._buffer:
            # no latency to emulate: the newest poses if they are new, without the buffer and its
            # copies (the flight loop reads once per tick; the poses are fresh arrays per frame)
            got = self._newest()
            if got is not None:
                return self._frame(*got)
            if timeout_s <= 0.0:
                return None
        deadline = time.monotonic() + max(timeout_s, 0.0)
        while True:
            got = self._delayed(self._poll() - self.latency_s)
            if got is not None:
                return self._frame(*got)
            if time.monotonic() >= deadline:
                return None
            time.sleep(0.001)

    def _delayed(self, target: float) -> tuple[float, dict] | None:
        """The scene at time ``target`` (now minus the latency), if it is later than the last frame
        delivered: the newest buffered sample at or before it, or, between two samples, both
        interpolated (position linear, attitude normalised linear; the simulated drones are read
        once per tick, so a latency that is not a multiple of the tick falls between samples)."""
        buf = self._buffer
        j = -1
        for i, (t, _) in enumerate(buf):
            if t <= target + 1e-9:
                j = i
        if j < 0:
            return None
        t0, a = buf[j]
        if j + 1 < len(buf) and target > t0 + 1e-9:
            t1, b = buf[j + 1]
            w = (target - t0) / (t1 - t0)
            raw = {body: interpolate_pose(*a[body], *b[body], w) for body in a.keys() & b.keys()}
            t0, a = target, raw
        if t0 <= self._delivered_t + 1e-9:
            return None
        del buf[:j]                # keep sample j: the next frame may fall between it and j + 1
        if t0 == buf[0][0]:
            del buf[0]
        self._delivered_t = t0
        return t0, a

    def _frame(self, t: float, raw: dict) -> MocapFrame:
        poses = {}
        for body in sorted(raw):            # sorted: the random stream does not depend on dict order
            pos, quat = raw[body]
            drop = self.dropout > 0 and self._rng.random() < self.dropout
            if self.noise_m > 0:
                pos, quat = perturb_pose(pos, quat, self._rng.standard_normal(3), self.noise_m)
            pose = finite_pose(pos, quat)
            if not drop and pose is not None:
                poses[body] = pose
        self._seq += 1
        return MocapFrame(t=t, poses=poses, seq=self._seq)


class _SubscriberPoses:
    """.poses() over a simcf PoseSubscriber (None until the first datagram)."""

    def __init__(self, sub):
        self.sub = sub

    def poses(self):
        return self.sub.latest()


class UdpSimSource(SimSource):
    """The pose stream of a SimCrazyflieServer in another process (`cfrace sim serve`)."""

    def __init__(self, spec: str, host: str, port: int, bodies: list[str], **kw):
        super().__init__(None, bodies, **kw)
        self.name, self.host, self.port = spec, host, port
        self._sub = None

    def open(self, timeout_s: float = 5.0) -> None:
        if self._opened:
            return
        from cfrace.simcf.poses import PoseSubscriber
        self._sub = PoseSubscriber(self.host, self.port)
        self.sim = _SubscriberPoses(self._sub)
        try:
            self._sub.wait(timeout_s)
            super().open(timeout_s)
        except MocapError as exc:
            self.close()
            raise MocapError(f"{self.name}: {exc}") from None

    def close(self) -> None:
        if self._sub is not None:
            self._sub.close()
            self._sub = None
        super().close()


# ---------------------------------------------------------------------------------------------
