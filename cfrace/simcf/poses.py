"""Ground-truth poses of the simulated drones over UDP (for the `sim` mocap source in another process).

The server publishes one datagram per clock tick to every subscriber. A subscriber sends any
datagram (b"SUB") to the pose port at least every 3 s to stay subscribed.

Frame (little endian): b"CFP1", t_sim float64 s, count uint32, then per body: name length uint8,
name (UTF-8), position x y z float64 m (world), quaternion w x y z float64 (world-from-body).
"""

from __future__ import annotations

import socket
import struct
import threading
import time

import numpy as np

from cfrace.errors import MocapError

MAGIC = b"CFP1"
SUBSCRIBE = b"SUB"
SUBSCRIPTION_TTL = 3.0   #: s a subscription lives without renewal
RENEW_PERIOD = 1.0       #: s between a subscriber's renewals


def encode_frame(t: float, bodies: dict) -> bytes:
    out = [MAGIC, struct.pack("<dI", t, len(bodies))]
    for name, (pos, quat) in bodies.items():
        raw = name.encode()[:255]
        out.append(struct.pack("<B", len(raw)) + raw + struct.pack("<7d", *np.asarray(pos, float), *np.asarray(quat, float)))
    return b"".join(out)


def decode_frame(data: bytes) -> tuple[float, dict]:
    """-> (t_sim, {name: (pos (3,), quat (4,) wxyz)}); ValueError on a malformed frame."""
    if data[:4] != MAGIC or len(data) < 16:
        raise ValueError("not a cfrace pose frame")
    t, n = struct.unpack_from("<dI", data, 4)
    k, bodies = 16, {}
    try:
        for _ in range(n):
            ln = data[k]
            name = data[k + 1:k + 1 + ln].decode()
            k += 1 + ln
            v = struct.unpack_from("<7d", data, k)
            k += 56
            bodies[name] = (np.array(v[:3]), np.array(v[3:]))
    except (IndexError, struct.error, UnicodeDecodeError) as e:
        raise ValueError(f"truncated cfrace pose frame: {e}") from None
    return t, bodies


class PoseSubscriber:
    """Receives pose frames from a SimCrazyflieServer's pose port in a background thread."""

    def __init__(self, host: str = "127.0.0.1", port: int = 19849):
        self.addr = (host, int(port))
        self._sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        self._sock.settimeout(0.1)
        self._latest: tuple[float, dict] | None = None
        self._cond = threading.Condition()
        self._stop = threading.Event()
        self.frames = 0
        self._thread = threading.Thread(target=self._run, name="simcf-pose-sub", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        last_sub = -1e9
        while not self._stop.is_set():
            now = time.monotonic()
            if now - last_sub >= RENEW_PERIOD:
                try:
                    self._sock.sendto(SUBSCRIBE, self.addr)
                except OSError:
                    pass
                last_sub = now
            try:
                data = self._sock.recv(4096)
            except (socket.timeout, OSError):
                continue
            try:
                frame = decode_frame(data)
            except ValueError:
                continue
            with self._cond:
                self._latest = frame
                self.frames += 1
                self._cond.notify_all()

    def latest(self) -> tuple[float, dict] | None:
        with self._cond:
            return self._latest

    def wait(self, timeout: float = 2.0) -> tuple[float, dict]:
        """The next frame; MocapError when none arrives in time."""
        with self._cond:
            seen = self.frames
            if not self._cond.wait_for(lambda: self.frames > seen, timeout):
                raise MocapError(f"no simulated poses from udp://{self.addr[0]}:{self.addr[1]} within "
                                 f"{timeout:.1f} s (is `cfrace sim serve` running?)")
            return self._latest

    def close(self) -> None:
        self._stop.set()
        self._thread.join(timeout=1.0)
        self._sock.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()
