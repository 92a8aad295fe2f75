"""The loop's end of the link keeper (cfrace.flight.link.keeper: the drones' links in a process of
their own): ``LinkKeeper`` spawns the keeper and talks to it through a socket pair, ``KeptLink`` is
one drone's Link (cfrace.flight.link.protocol) through it. The messages are cfrace.flight.link.keeper's."""

from __future__ import annotations

import json
import queue
import socket
import struct
import subprocess
import sys
import threading
from multiprocessing.connection import Connection
from pathlib import Path

from cfrace.errors import LinkError
from cfrace.flight.link.protocol import LinkQuality
from cfrace.flight.link.keeper import POSE_MSG, SETPOINT_MSG, SPAWN_TIMEOUT_S


class LinkKeeper:
    """The loop's end: spawns the keeper on the first connect; ``link(i)`` is drone i's Link."""

    def __init__(self, uris, *, heartbeat_s: float, stop_log: str | Path | None = None, rt_priority: int = 0,
                 cpus=None, estop_watchdog: bool = False):
        self.uris = list(uris)
        self.estop_watchdog = bool(estop_watchdog)
        self.rt_priority, self.cpus = int(rt_priority), sorted(cpus) if cpus else None
        self.heartbeat_s = float(heartbeat_s)
        self.stop_log = str(stop_log) if stop_log else None
        if self.stop_log:   # beside the flight log, whose folder (default flights/) may not exist yet
            Path(self.stop_log).parent.mkdir(parents=True, exist_ok=True)
        self.qualities = [LinkQuality() for _ in self.uris]
        self._proc = None
        self._conn = None
        self._replies: queue.Queue = queue.Queue()
        self._reader: threading.Thread | None = None
        self._send_lock = threading.Lock()
        self._open_links = 0

    def link(self, i: int) -> "KeptLink":
        self._open_links += 1
        return KeptLink(self, i)

    def start(self) -> None:
        if self._proc is not None:
            return
        # a plain child process (not multiprocessing's spawn, which re-imports the parent's main
        # script): `python -m cfrace.flight.link.keeper FD` with one end of a socket pair
        here, there = socket.socketpair()
        args = json.dumps({"uris": self.uris, "heartbeat_s": self.heartbeat_s, "stop_log": self.stop_log,
                           "rt_priority": self.rt_priority, "cpus": self.cpus, "estop_watchdog": self.estop_watchdog})
        self._proc = subprocess.Popen([sys.executable, "-m", "cfrace.flight.link.keeper", str(there.fileno()), args],
                                      pass_fds=(there.fileno(),), stdin=subprocess.DEVNULL)
        there.close()
        self._conn = Connection(here.detach())
        self._reader = threading.Thread(target=self._read, name="link-keeper-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        conn = self._conn
        while True:
            try:
                msg = conn.recv_bytes()
            except (EOFError, OSError):
                for q in self.qualities:
                    q.connected = False
                    q.error = q.error or "link keeper process ended"
                self._replies.put({"ok": False, "error": "the link keeper process ended"})
                return
            if msg[:1] == b"r":
                self._replies.put(json.loads(msg[1:]))
            elif msg[:1] == b"l":
                for i, f in json.loads(msg[1:]).items():
                    q = self.qualities[int(i)]
                    for k, v in f.items():
                        setattr(q, k, v)

    def _post(self, msg: bytes) -> None:
        conn = self._conn
        if conn is None:
            return
        with self._send_lock:
            conn.send_bytes(msg)

    def request(self, kind: bytes, i: int, wait_s: float, **body) -> dict:
        self.start()
        try:
            self._post(kind + json.dumps({"drone": i, **body}).encode())
        except OSError:
            raise LinkError(f"{self.uris[i]}: the link keeper process is gone") from None
        try:
            reply = self._replies.get(timeout=wait_s + SPAWN_TIMEOUT_S)
        except queue.Empty:
            raise LinkError(f"{self.uris[i]}: the link keeper did not answer") from None
        if not reply.get("ok"):
            raise LinkError(reply.get("error", f"{self.uris[i]}: link failed"))
        return reply

    def send(self, i: int, p: float, q: float, r: float, counts: int) -> None:
        try:
            self._post(SETPOINT_MSG.pack(b"s", i, p, q, r, counts))
        except (OSError, struct.error):
            self.qualities[i].connected = False

    def stop(self, i: int) -> None:
        try:
            self._post(b"x" + bytes([i]))
        except OSError:
            pass

    def send_pose(self, i: int, pos, quat) -> None:
        try:
            self._post(POSE_MSG.pack(b"p", i, *(float(v) for v in pos), *(float(v) for v in quat)))
        except (OSError, struct.error):
            pass

    def command(self, i: int, command: str, args: dict) -> None:
        try:
            self._post(b"h" + json.dumps({"drone": i, "command": command, "args": args}).encode())
        except OSError:
            self.qualities[i].connected = False

    def release(self) -> None:
        """One link closed; after the last, the keeper stops everything and ends."""
        self._open_links -= 1
        if self._open_links > 0 or self._proc is None:
            return
        try:
            self._post(b"q")
        except OSError:
            pass
        try:
            self._proc.wait(5.0)
        except subprocess.TimeoutExpired:
            self._proc.terminate()
            self._proc.wait(2.0)
        self._conn.close()
        self._conn, self._proc = None, None


class KeptLink:
    """A Link (cfrace.flight.link.protocol) to drone i through the link keeper."""

    def __init__(self, keeper: LinkKeeper, i: int):
        self.keeper, self.i = keeper, int(i)
        self.uri = keeper.uris[i]
        self.quality = keeper.qualities[i]
        self._closed = False

    def connect(self, timeout_s: float) -> None:
        self.keeper.request(b"c", self.i, timeout_s, timeout_s=timeout_s)

    def setup(self) -> None:
        self.keeper.request(b"u", self.i, 5.0)

    def send(self, roll_rate_dps, pitch_rate_dps, yaw_rate_dps, thrust_counts) -> None:
        self.keeper.send(self.i, float(roll_rate_dps), float(pitch_rate_dps), float(yaw_rate_dps), int(thrust_counts))
        self.quality.sent += 1

    def stop(self) -> None:
        self.keeper.stop(self.i)

    def send_pose(self, pos, quat) -> None:
        self.keeper.send_pose(self.i, pos, quat)

    def high_level(self, command: str, **args) -> None:
        self.keeper.command(self.i, command, args)

    def notify_stop(self) -> None:
        self.keeper.command(self.i, "notify_stop", {})

    def read_status(self, timeout_s: float = 2.0) -> dict:
        return self.keeper.request(b"v", self.i, timeout_s)["status"]

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            self.stop()
            self.keeper.release()
