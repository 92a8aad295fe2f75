"""Links held by a process of their own (the link keeper), so that no drone flies on when the
flight loop's process dies or hangs.

The keeper is a small child process: it opens the cflib links (CflibLink), forwards each setpoint
the loop sends through a pipe, keeps cflib's pings and threads (they no longer share the loop's
GIL) and reports every link's figures back. It stops every flying drone (zero setpoint, STOP
setpoint, disarm) the moment

- the pipe closes (the loop's process exited or was killed, even by ``kill -9``: the kernel closes
  its end), or
- no setpoint came for ``heartbeat_s`` while a drone flies (a hung loop; the loop's own
  ``loop_overrun`` rule stops every drone at the same lateness), or
- it gets SIGTERM (SIGINT is ignored: a Ctrl-C reaches the whole process group and is the loop's
  to handle).

With ``estop_watchdog`` it also feeds the firmware's emergency-stop watchdog of every flying drone
every ESTOP_FEED_S: a drone that hears nothing for 1 s (its link lost, or the keeper gone too) then
cuts its own motors, and stays locked until it is rebooted.

A drone stopped by the keeper stays stopped: later setpoints for it are dropped and its link
reports disconnected, so the loop's safety check stops it too. Every stop is timestamped where it
is sent (time.monotonic and the wall clock, in the keeper) and appended to ``stop_log`` (JSON
lines) when one is given; a stop because the loop is gone is also one line on stderr.

Messages on the pipe (bytes; first byte the kind): loop -> keeper ``s`` setpoint, ``x`` stop,
``p`` pose (external position), ``h`` high-level command or notify-stop (JSON), ``c`` connect,
``u`` set up, ``v`` status (pre-flight checks), ``q`` quit; keeper -> loop ``r`` reply (JSON), ``l`` link figures (JSON,
every REPORT_S and on every change of connection or stop).
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import struct
import subprocess
import sys
import threading
import time
from multiprocessing.connection import Connection
from pathlib import Path

from cfrace.errors import LinkError
from cfrace.flight.link import LinkQuality
from cfrace.flight.realtime import set_fifo

REPORT_S = 0.05            #: s between link figure reports (keeper -> loop)
ESTOP_FEED_S = 0.1         #: s between feeds of a flying drone's emergency-stop watchdog (the firmware's: 1 s)
SPAWN_TIMEOUT_S = 20.0     #: s for the keeper to start (it imports cflib)
CLOSE_S = 2.0              #: s the keeper waits for its links to close before it ends
_SETPOINT = struct.Struct("<cBfffH")    # b"s", drone, p, q, r (deg/s), thrust counts
_POSE = struct.Struct("<cB7f")          # b"p", drone, x, y, z (m), qw, qx, qy, qz


# ---------------------------------------------------------------------------------- keeper side
class _Keeper:
    """The child's state: its links, which drones fly, when the loop was last heard."""

    def __init__(self, conn, uris: list[str], heartbeat_s: float, stop_log: str | None, rt_priority: int = 0,
                 estop_watchdog: bool = False):
        from cfrace.flight.link_cflib import CflibLink   # cflib only in the keeper

        self.conn, self.heartbeat_s = conn, float(heartbeat_s)
        self.links = [CflibLink(u) for u in uris]
        self.flying = [False] * len(uris)
        self.dead = [False] * len(uris)       #: stopped by the keeper: setpoints for it are dropped
        self.stop_log = open(stop_log, "a", buffering=1) if stop_log else None   # noqa: SIM115
        self.last_heard = time.monotonic()
        self.last_report = 0.0
        self.changed = False
        self.rt_priority = rt_priority   #: SCHED_FIFO for all the keeper's threads from the first setpoint
        self.estop_watchdog = bool(estop_watchdog)
        self.last_feed = 0.0

    def stop(self, i: int, why: str) -> None:
        """Stop drone i now and record where and when the stop was sent."""
        t_mono, t_wall = time.monotonic(), time.time()
        self.links[i].stop()
        was_flying, self.flying[i] = self.flying[i], False
        if why != "loop":
            self.dead[i] = True
        self.changed = True
        rec = {"drone": i, "uri": self.links[i].uri, "why": why, "was_flying": was_flying,
               "t_mono": t_mono, "t_wall": t_wall, "stop_sent_s": time.monotonic() - t_mono,
               "since_loop_s": t_mono - self.last_heard}   # since the loop's last message
        if self.stop_log is not None:
            self.stop_log.write(json.dumps(rec) + "\n")
        if why != "loop" and was_flying:
            print(f"link keeper: stopped {self.links[i].uri} ({why})", file=sys.stderr, flush=True)

    def stop_all(self, why: str) -> None:
        for i in range(len(self.links)):
            if self.flying[i] or why != "loop":
                self.stop(i, why)

    def report(self, now: float) -> None:
        figures = {}
        for i, link in enumerate(self.links):
            q = link.quality
            figures[i] = {"connected": q.connected and not self.dead[i], "last_rx": q.last_rx,
                          "latency_ms": q.latency_ms, "link_quality": q.link_quality, "sent": q.sent, "vbat": q.vbat,
                          "errors": q.errors, "error": q.error if not self.dead[i] else "stopped by the link keeper"}
        self.conn.send_bytes(b"l" + json.dumps(figures).encode())
        self.last_report, self.changed = now, False

    def request(self, kind: bytes, body: dict) -> None:
        """c / u: connect or set up one link; the reply says ok or the LinkError's line."""
        i = int(body["drone"])
        try:
            if kind == b"c":
                self.links[i].connect(float(body["timeout_s"]))
                reply = {"ok": True}
            elif kind == b"v":
                reply = {"ok": True, "status": self.links[i].read_status()}
            else:
                self.links[i].setup()
                reply = {"ok": True}
        except LinkError as exc:
            reply = {"ok": False, "error": str(exc)}
        self.report(time.monotonic())    # the figures first: the loop reads them once the reply is in
        self.conn.send_bytes(b"r" + json.dumps(reply).encode())

    def handle(self, msg: bytes) -> bool:
        """One message from the loop; False once the keeper must end."""
        kind = msg[:1]
        if kind == b"s":
            if self.rt_priority:   # the race has started: as the loop, its links do not wait behind
                set_fifo(self.rt_priority)   # the machine's ordinary jobs (cfrace.flight.realtime)
                self.rt_priority = 0
            _, i, p, q, r, counts = _SETPOINT.unpack(msg)
            if not self.dead[i]:
                self.links[i].send(p, q, r, counts)
                self.flying[i] = True
        elif kind == b"p":
            _, i, *v = _POSE.unpack(msg)
            if not self.dead[i]:
                self.links[i].send_pose(v[:3], v[3:])
        elif kind == b"h":      # a high-level command or notify-stop: the drone flies on its firmware
            body = json.loads(msg[1:])
            i = int(body["drone"])
            if not self.dead[i]:
                if body["command"] == "notify_stop":
                    self.links[i].notify_stop()
                else:
                    self.links[i].high_level(body["command"], **body["args"])
                self.flying[i] = body["command"] != "stop"
        elif kind == b"x":
            self.stop(msg[1], "loop")
        elif kind in (b"c", b"u", b"v"):
            self.request(kind, json.loads(msg[1:]))
        elif kind == b"q":
            return False
        return True

    def feed(self, now: float) -> None:
        """Feed the emergency-stop watchdog of every flying drone (a dead link's feed is lost)."""
        self.last_feed = now
        for i, link in enumerate(self.links):
            if self.flying[i] and not self.dead[i]:
                link.feed_estop_watchdog()

    def run(self) -> None:
        while True:
            now = time.monotonic()
            wait = REPORT_S - (now - self.last_report)
            if any(self.flying):
                wait = min(wait, self.heartbeat_s - (now - self.last_heard))
                if self.estop_watchdog:
                    wait = min(wait, ESTOP_FEED_S - (now - self.last_feed))
            try:
                ready = self.conn.poll(max(0.0, wait))
                if ready:
                    msg = self.conn.recv_bytes()
            except (EOFError, OSError):
                self.stop_all("loop_gone")
                return
            now = time.monotonic()
            if ready:
                self.last_heard = now
                if not self.handle(msg):
                    self.stop_all("quit")
                    return
            elif any(self.flying) and now - self.last_heard > self.heartbeat_s:
                self.stop_all("heartbeat")
            if self.estop_watchdog and any(self.flying) and now - self.last_feed >= ESTOP_FEED_S:
                self.feed(now)
            if self.changed or now - self.last_report >= REPORT_S:
                try:
                    self.report(now)
                except OSError:
                    pass

    def close(self) -> None:
        for link in self.links:
            try:
                link.close()
            except Exception:  # noqa: BLE001 - every link must be closed
                pass
        if self.stop_log is not None:
            self.stop_log.close()


def _pin(cpus) -> None:
    """The keeper's CPUs (not the loop's), before any cflib thread starts (they inherit them)."""
    try:
        if cpus:
            os.sched_setaffinity(0, set(cpus))
    except (OSError, AttributeError):
        pass   # not permitted / not Linux


def keeper_main(conn, uris: list[str], heartbeat_s: float, stop_log: str | None, rt_priority: int = 0,
                cpus=None, estop_watchdog: bool = False) -> None:
    """The keeper process's entry point."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    _pin(cpus)
    keeper = _Keeper(conn, uris, heartbeat_s, stop_log, rt_priority, estop_watchdog)

    def on_term(signum, frame):
        keeper.stop_all("sigterm")
        _close_and_exit(keeper)

    signal.signal(signal.SIGTERM, on_term)
    try:
        keeper.run()
    finally:
        _close_and_exit(keeper)


def _close_and_exit(keeper: _Keeper) -> None:
    """Close the links (their stops are sent already) for at most CLOSE_S, then end the process: a
    link whose radio or relay went away can block cflib's close, and its threads the exit."""
    closer = threading.Thread(target=keeper.close, name="link-keeper-close", daemon=True)
    closer.start()
    closer.join(CLOSE_S)
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


# ------------------------------------------------------------------------------------ loop side
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
        # script): `python -m cfrace.flight.linkproc FD` with one end of a socket pair
        here, there = socket.socketpair()
        args = json.dumps({"uris": self.uris, "heartbeat_s": self.heartbeat_s, "stop_log": self.stop_log,
                           "rt_priority": self.rt_priority, "cpus": self.cpus, "estop_watchdog": self.estop_watchdog})
        self._proc = subprocess.Popen([sys.executable, "-m", "cfrace.flight.linkproc", str(there.fileno()), args],
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
            self._post(_SETPOINT.pack(b"s", i, p, q, r, counts))
        except (OSError, struct.error):
            self.qualities[i].connected = False

    def stop(self, i: int) -> None:
        try:
            self._post(b"x" + bytes([i]))
        except OSError:
            pass

    def send_pose(self, i: int, pos, quat) -> None:
        try:
            self._post(_POSE.pack(b"p", i, *(float(v) for v in pos), *(float(v) for v in quat)))
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
    """A Link (cfrace.flight.link) to drone i through the link keeper."""

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


if __name__ == "__main__":
    _opts = json.loads(sys.argv[2])
    keeper_main(Connection(int(sys.argv[1])), _opts["uris"], _opts["heartbeat_s"], _opts["stop_log"],
                _opts["rt_priority"], _opts["cpus"], _opts.get("estop_watchdog", False))
