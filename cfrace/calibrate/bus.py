"""The stand's CAN bus (python-can): ``can://INTERFACE/CHANNEL[?bitrate=N]`` and the sensor reader.

Interfaces are python-can's: ``socketcan`` (can0, vcan0), ``pcan``, ``kvaser``, ``slcan``...
for hardware, ``virtual`` (in-process) and ``udp_multicast`` (across processes on this machine,
channel = a multicast group, e.g. 239.74.163.2) for the simulated stand.
"""

from __future__ import annotations

import math
import struct
import threading
import time
from dataclasses import dataclass
from urllib.parse import parse_qs, urlsplit

import numpy as np

from cfrace.calibrate.sensor import QUANTITIES, SensorSpec
from cfrace.errors import CfraceError, ConfigError


class StandError(CfraceError):
    """The stand stopped the run: CAN timeout, a reading beyond range, link loss, refused start."""


@dataclass(frozen=True)
class BusSpec:
    interface: str
    channel: str
    bitrate: int | None = None

    def __str__(self) -> str:
        return f"can://{self.interface}/{self.channel}" + (f"?bitrate={self.bitrate}" if self.bitrate else "")


def parse_bus(text: str) -> BusSpec:
    """``can://INTERFACE/CHANNEL[?bitrate=N]`` -> BusSpec; ConfigError naming what is wrong."""
    u = urlsplit(text)
    if u.scheme != "can" or not u.netloc or not u.path.strip("/"):
        raise ConfigError(f"--bus {text!r}: expected can://INTERFACE/CHANNEL, e.g. can://socketcan/can0, "
                          "can://virtual/stand or can://udp_multicast/239.74.163.2")
    query = parse_qs(u.query)
    extra = sorted(set(query) - {"bitrate"})
    if extra:
        raise ConfigError(f"--bus {text!r}: unknown option {extra[0]!r} (only bitrate)")
    bitrate = None
    if "bitrate" in query:
        try:
            bitrate = int(query["bitrate"][0])
        except ValueError:
            raise ConfigError(f"--bus {text!r}: bitrate must be an integer") from None
    return BusSpec(u.netloc, u.path.strip("/"), bitrate)


def open_bus(spec: BusSpec | str, **kw):
    """A python-can Bus, or ConfigError / StandError with one line."""
    import can

    spec = parse_bus(spec) if isinstance(spec, str) else spec
    if spec.bitrate:
        kw["bitrate"] = spec.bitrate
    try:
        return can.Bus(interface=spec.interface, channel=spec.channel, **kw)
    except (can.CanInterfaceNotImplementedError, ImportError) as e:
        raise ConfigError(f"{spec}: interface {spec.interface!r} not available ({str(e).splitlines()[0]})") from None
    except (can.CanError, OSError, ValueError) as e:
        raise StandError(f"{spec}: cannot open the CAN bus ({str(e).splitlines()[0] if str(e) else type(e).__name__})") from None


class SensorReader:
    """Reads the sensor's frames on a thread and assembles samples.

    Arrays of what was received (``samples()``): host time (s, time.monotonic at arrival), sensor
    time (s: the counter over rate_hz when the sensor sends one, else the host time) and the
    (6,) wrench in the body frame about the drone's centre, bias removed once ``tare`` ran.
    ``fault`` is set (and stays) at the first reading beyond the sensor's range or saturated."""

    def __init__(self, bus, sensor: SensorSpec, where: str = "CAN bus"):
        self.bus = bus
        self.sensor = sensor
        self.where = where
        self._ids = {(fr.can_id, fr.extended): k for k, fr in enumerate(sensor.frames)}
        self._lock = threading.Lock()
        self._host: list[float] = []
        self._stime: list[float] = []
        self._raw: list[np.ndarray] = []     # (6,) body frame, bias not removed
        self.bias = np.zeros(6)
        self.fault: str | None = None
        self.last_sample: float | None = None   #: host time of the newest complete sample
        self.last_poll: float | None = None     #: host time the reader last came back from the bus
        self.bad_frames = 0                     #: frames that did not decode or broke a sample apart
        self._partial: dict = {}
        self._counter_base = 0
        self._counter_last: int | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="stand-can", daemon=True)

    def start(self) -> "SensorReader":
        self._thread.start()
        return self

    def stop(self) -> None:
        self._stop.set()
        self._thread.join(timeout=2.0)

    def _run(self) -> None:
        order = len(self.sensor.frames) - 1
        while not self._stop.is_set():
            try:
                msg = self.bus.recv(timeout=0.02)
            except Exception as e:   # a bus that dies: the timeout check reports silence
                self.fault = self.fault or f"{self.where}: bus error ({' '.join(str(e).split())[:120]})"
                return
            self.last_poll = time.monotonic()
            if msg is None or msg.is_error_frame or msg.is_remote_frame:
                continue
            k = self._ids.get((msg.arbitration_id, bool(msg.is_extended_id)))
            if k is None:
                continue
            try:
                values, sat = self.sensor.decode(k, bytes(msg.data))
            except (ValueError, struct.error):
                self.bad_frames += 1
                continue
            if k == 0:
                self._partial = {}
            if "counter" in values and self._partial.get("counter", values["counter"]) != values["counter"]:
                self.bad_frames += 1
                self._partial = {}
                continue
            self._partial.update(values)
            self._partial["_sat"] = self._partial.get("_sat", False) or sat
            if k == order:
                self._complete(self._partial)
                self._partial = {}

    def _complete(self, p: dict) -> None:
        if any(q not in p for q in QUANTITIES):
            self.bad_frames += 1
            return
        now = time.monotonic()
        body = self.sensor.to_body(np.array([p[q] for q in QUANTITIES]))
        if "counter" in p:
            c = int(p["counter"])
            hi = self.sensor.counter.limits[1]
            if self._counter_last is not None and c < self._counter_last:
                self._counter_base += hi + 1
            self._counter_last = c
            stime = (self._counter_base + c) / self.sensor.rate_hz
        else:
            stime = now
        with self._lock:
            self._host.append(now)
            self._stime.append(stime)
            self._raw.append(body)
            self.last_sample = now
        if self.fault is None:
            self.fault = self._check(body, p["_sat"])

    def _check(self, body: np.ndarray, saturated: bool) -> str | None:
        if saturated:
            return f"{self.where}: the sensor saturated (a raw reading at its converter's limit)"
        w = body - self.bias
        names = ("fx", "fy", "fz", "tx", "ty", "tz")
        limits = self.sensor.force_range + self.sensor.torque_range
        for k in range(6):
            if abs(w[k]) > limits[k]:
                unit = "N" if k < 3 else "N m"
                return (f"{self.where}: {names[k]} = {w[k]:.3g} {unit} beyond the sensor's range "
                        f"{limits[k]:g} {unit}")
        return None

    def silent_for(self) -> float | None:
        """s the reader has listened without a complete sample (None: not listened since the last one).
        Counts only time the reader thread actually ran: a host that stalls is not a silent sensor."""
        last, poll = self.last_sample, self.last_poll
        if last is None:
            return None if poll is None else math.inf
        return poll - last if poll is not None and poll > last else None

    def count(self) -> int:
        with self._lock:
            return len(self._host)

    def samples(self, start: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """(host (n,), sensor time (n,), wrench (n, 6) minus bias) from sample index ``start``."""
        with self._lock:
            host, st, raw = np.array(self._host[start:]), np.array(self._stime[start:]), list(self._raw[start:])
        w = np.array(raw).reshape(-1, 6) - self.bias
        return host, st, w

    def wait_samples(self, n: int, timeout_s: float) -> None:
        """Block until n more samples arrived, else StandError (a silent bus)."""
        start = self.count()
        t_end = time.monotonic() + timeout_s
        while self.count() - start < n:
            if time.monotonic() > t_end:
                got = self.count() - start
                what = "no frame" if got == 0 else f"only {got} of {n} samples"
                raise StandError(f"{self.where}: {what} from the sensor (ids {self.sensor.ids()}) within "
                                 f"{timeout_s:g} s: is it powered and on this bus?")
            if self.fault:
                raise StandError(self.fault)
            time.sleep(0.005)

    def tare(self) -> np.ndarray:
        """Bias = the mean of the last tare_samples samples (motors off). Returns it."""
        with self._lock:
            raw = np.array(self._raw[-self.sensor.tare_samples:])
        self.bias = raw.mean(0)
        return self.bias
