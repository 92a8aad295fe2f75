"""Motion-capture sources: real systems (via the `motioncapture` package), log replay and simulation.

`open_mocap(spec, bodies=[...])` returns an unopened MocapSource; `open()` connects and checks that
every required body is seen, `read()` returns the newest frame (or None when nothing new arrived),
`close()` releases it. Sources are also context managers. Specs:

    vicon://HOST  optitrack://HOST  qualisys://HOST  vrpn://HOST   real systems (libmotioncapture)
    replay://FILE.mcap[?speed=S]   the /mocap/pose messages of a cfrace flight log; S = 1 recorded
                                   pace, S > 1 faster, S = 0 lockstep (one frame per read, no waiting)
    sim                            poses from an object with .poses() -> (t_s, {body: (pos, quat)})
                                   (SimFleet, SimCrazyflieServer) with optional noise/latency/dropout
    sim://HOST:PORT                the same from a SimCrazyflieServer's pose port in another process

Real systems run in a worker process (`python -m cfrace.flight.mocap.sources --worker TYPE HOST`):
libmotioncapture's connect() holds the GIL and blocks forever when no server answers, which would
freeze the whole flight process. The worker streams JSON lines; frame times are its
time.monotonic() at reception (the same system-wide clock as the flight loop's).
Occluded bodies are absent from a frame; non-finite poses are dropped like occlusions.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from pathlib import Path

from cfrace.errors import CfraceError, MocapError
from cfrace.flight.mocap.base import (MocapFrame, MocapSource, Pose, SourceBase, finite_pose, frame_from_msg,
                                      frame_to_msg)
from cfrace.flight.mocap.simulated import SimSource, UdpSimSource

__all__ = ["open_mocap", "MocapFrame", "MocapSource", "Pose", "frame_from_msg", "frame_to_msg", "SystemSource",
           "ReplaySource", "SimSource", "UdpSimSource", "SYSTEMS"]

SYSTEMS = ("vicon", "optitrack", "qualisys", "vrpn")   #: libmotioncapture types we expose
_SPEC_HELP = ("vicon://HOST, optitrack://HOST, qualisys://HOST, vrpn://HOST, "
              "replay://FILE.mcap[?speed=S], sim or sim://HOST:PORT")



class SystemSource(SourceBase):
    """Vicon / OptiTrack / Qualisys / VRPN through a `motioncapture` worker process."""

    def __init__(self, spec: str, kind: str, host: str, bodies: list[str]):
        super().__init__(spec, bodies)
        self.kind, self.host = kind, host
        self._proc: subprocess.Popen | None = None
        self._cond = threading.Condition()
        self._connected = threading.Event()
        self._latest: MocapFrame | None = None
        self._returned_seq = 0
        self.error: str | None = None   #: set when the worker reported an error or died

    def open(self, timeout_s: float = 5.0) -> None:
        if self._opened:
            return
        self._connected, self.error = threading.Event(), None
        self._latest, self._returned_seq = None, 0
        self._proc = subprocess.Popen(
            [sys.executable, "-m", "cfrace.flight.mocap.sources", "--worker", self.kind, self.host],
            stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=subprocess.DEVNULL)
        self._pump_thread = threading.Thread(target=self._pump, daemon=True, name=f"mocap-{self.kind}")
        self._pump_thread.start()
        if not self._connected.wait(timeout_s):
            self._kill()
            raise MocapError(f"{self.name}: no answer within {timeout_s:.1f} s ({self._hint()})")
        if self.error is not None:
            self._kill()
            raise MocapError(f"{self.name}: could not connect ({self._hint()}; the {self.kind} client said: "
                             f"{self.error})")
        deadline = time.monotonic() + timeout_s
        while self._missing() and time.monotonic() < deadline and self.error is None:
            with self._cond:
                self._cond.wait(0.05)
        if self.error is not None:
            self._kill()
            raise MocapError(f"{self.name}: {self.error}")
        if self._missing():
            self._kill()
            raise self._body_error()
        self._opened = True

    def _hint(self) -> str:
        """What to check when the system does not answer."""
        return (f"is the {self.kind} server running on '{self.host}' and streaming, and is '{self.host}' its "
                f"address as seen from this machine?")

    def _pump(self) -> None:
        """Reader thread: worker JSON lines -> latest frame."""
        proc, seq = self._proc, 0
        assert proc is not None and proc.stdout is not None
        for line in proc.stdout:
            try:
                msg = json.loads(line)
            except ValueError:
                continue
            if not isinstance(msg, dict):
                continue
            if "error" in msg:
                self.error = str(msg["error"])
                self._connected.set()
                break
            if msg.get("connected"):
                self._connected.set()
                continue
            try:
                t = float(msg["t"])
                poses = {body: pose for body, v in msg["b"].items()
                         if (pose := finite_pose(v[:3], v[3:7])) is not None}
            except (KeyError, TypeError, ValueError, AttributeError):
                continue
            seq += 1
            with self._cond:
                self._seen.update(poses)
                self._latest = MocapFrame(t=t, poses=poses, seq=seq)
                self._cond.notify_all()
        code = proc.wait()
        if self._proc is not proc:       # a reopen started a new worker meanwhile
            return
        if self.error is None:
            self.error = f"mocap worker exited (code {code})"
        self._connected.set()            # an open() still waiting fails now, with the error
        with self._cond:
            self._cond.notify_all()

    def read(self, timeout_s: float = 0.02) -> MocapFrame | None:
        if not self._opened:
            self.open()
        with self._cond:
            if self._latest is None or self._latest.seq <= self._returned_seq:
                self._cond.wait(timeout_s)
            frame = self._latest
            if frame is None or frame.seq <= self._returned_seq:
                return None
            self._returned_seq = frame.seq
            return frame

    def _kill(self) -> None:
        if self._proc is not None and self._proc.poll() is None:
            self._proc.kill()
            try:
                self._proc.wait(2.0)
            except subprocess.TimeoutExpired:
                pass

    def close(self) -> None:
        self._kill()
        thread = getattr(self, "_pump_thread", None)
        if thread is not None and thread is not threading.current_thread():
            thread.join(2.0)
        super().close()


def _die_with_parent() -> None:
    """Linux: let the kernel kill this worker when the flight process dies (even by SIGKILL)."""
    try:
        import ctypes
        import signal
        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGKILL)   # PR_SET_PDEATHSIG
    except (OSError, AttributeError):
        pass


def _worker(kind: str, host: str) -> int:
    """Worker process: connect, then one JSON line per frame on stdout until the pipe closes."""
    import os
    _die_with_parent()
    out = os.fdopen(os.dup(1), "w")   # our protocol keeps the pipe; anything the C++ library
    os.dup2(2, 1)                     # prints to stdout goes to stderr instead

    def send(obj) -> None:
        out.write(json.dumps(obj) + "\n")
        out.flush()

    try:
        import motioncapture
        mc = motioncapture.connect(kind, {"hostname": host})
        send({"connected": True})
        while True:
            mc.waitForNextFrame()
            t = time.monotonic()
            bodies = {}
            for name, rb in mc.rigidBodies.items():
                p, q = rb.position, rb.rotation
                bodies[name] = [float(p[0]), float(p[1]), float(p[2]),
                                float(q.w), float(q.x), float(q.y), float(q.z)]
            send({"t": t, "b": bodies})
    except (BrokenPipeError, KeyboardInterrupt):
        return 0
    except Exception as exc:   # noqa: BLE001 - reported to the parent as one line
        try:
            send({"error": f"{type(exc).__name__}: {exc}"})
        except BrokenPipeError:
            pass
        return 1


# ---------------------------------------------------------------------------------------------
# replay of a flight log

class ReplaySource(SourceBase):
    """/mocap/pose messages of a cfrace flight log, at `speed` x the recorded pace (0: lockstep)."""

    def __init__(self, spec: str, path: Path, bodies: list[str], speed: float):
        super().__init__(spec, bodies)
        self.path, self.speed = path, speed
        self.frames: list[MocapFrame] = []
        self._i = 0
        self._start: float | None = None

    @property
    def done(self) -> bool:
        """True once every recorded frame has been returned or skipped."""
        return self._opened and self._i >= len(self.frames)

    def open(self, timeout_s: float = 5.0) -> None:
        if self._opened:
            return
        from cfrace.flight.log.writer import read_log
        try:
            data = read_log(self.path)
            self.frames = [frame_from_msg(m) for _, m in data.messages("/mocap/pose")]
        except CfraceError as exc:
            raise MocapError(f"{self.name}: {exc}") from None
        except (KeyError, TypeError, ValueError) as exc:
            raise MocapError(f"{self.name}: malformed /mocap/pose message ({exc})") from None
        if not self.frames:
            raise MocapError(f"{self.name}: the log holds no /mocap/pose messages")
        for frame in self.frames:
            self._seen.update(frame.poses)
        if self._missing():
            raise self._body_error()
        self._i, self._start = 0, None
        self._opened = True

    def read(self, timeout_s: float = 0.02) -> MocapFrame | None:
        if not self._opened:
            self.open()
        if self._i >= len(self.frames):
            return None
        if self.speed == 0:
            self._i += 1
            return self.frames[self._i - 1]
        now = time.monotonic()
        if self._start is None:
            self._start = now
        t0 = self.frames[0].t

        def due(k: int) -> float:
            return self._start + (self.frames[k].t - t0) / self.speed

        wait = due(self._i) - now
        if wait > 0:
            time.sleep(min(wait, max(timeout_s, 0.0)))
            if wait > timeout_s:
                return None
            now = max(time.monotonic(), due(self._i))
        j = self._i
        while j + 1 < len(self.frames) and due(j + 1) <= now:
            j += 1                      # a slow reader gets the newest frame, like a live system
        self._i = j + 1
        return self.frames[j]


def open_mocap(spec: str, *, bodies: list[str], sim=None, noise_m: float = 0.0,
               latency_s: float = 0.0, dropout: float = 0.0, seed: int = 0,
               speed: float = 1.0) -> MocapSource:
    """A MocapSource for `spec` (not yet opened: call .open() or use it as a context manager).
    Raises MocapError naming the spec if it is malformed."""
    spec = str(spec).strip()
    if not (noise_m >= 0 and latency_s >= 0 and 0 <= dropout < 1 and speed >= 0):
        raise MocapError(f"mocap '{spec}': need noise_m >= 0, latency_s >= 0, 0 <= dropout < 1, "
                         f"speed >= 0 (got {noise_m}, {latency_s}, {dropout}, {speed})")
    if spec == "sim":
        if sim is None or not callable(getattr(sim, "poses", None)):
            raise MocapError("mocap 'sim' needs a simulator with .poses() (only in sim flights)")
        return SimSource(sim, bodies, noise_m, latency_s, dropout, seed)
    kind, sep, rest = spec.partition("://")
    if kind == "sim" and sep:
        host, _, port = rest.rpartition(":")
        if not host or not port.isdigit() or not 0 < int(port) < 65536:
            raise MocapError(f"bad mocap spec '{spec}': expected sim://HOST:PORT (a simcf pose port)")
        return UdpSimSource(spec, host, int(port), bodies, noise_m=noise_m, latency_s=latency_s,
                            dropout=dropout, seed=seed)
    if not sep or not rest:
        raise MocapError(f"bad mocap spec '{spec}': expected {_SPEC_HELP}")
    if kind in SYSTEMS:
        if any(c in rest for c in "/?# ") or rest.startswith(":"):
            raise MocapError(f"bad mocap spec '{spec}': expected {kind}://HOST")
        return SystemSource(spec, kind, rest, bodies)
    if kind == "replay":
        file, _, query = rest.partition("?")
        if query:
            key, _, value = query.partition("=")
            try:
                if key != "speed":
                    raise ValueError
                speed = float(value)
                if not speed >= 0 or speed == float("inf"):
                    raise ValueError
            except ValueError:
                raise MocapError(f"bad mocap spec '{spec}': expected ?speed=S with S >= 0") from None
        path = Path(file).expanduser()
        if not path.is_file():
            raise MocapError(f"mocap '{spec}': no such file {path}")
        return ReplaySource(spec, path, bodies, speed)
    raise MocapError(f"bad mocap spec '{spec}': unknown system '{kind}' (expected {_SPEC_HELP})")


if __name__ == "__main__":
    if len(sys.argv) == 4 and sys.argv[1] == "--worker":
        sys.exit(_worker(sys.argv[2], sys.argv[3]))
    print("usage: python -m cfrace.flight.mocap.sources --worker TYPE HOST", file=sys.stderr)
    sys.exit(2)
