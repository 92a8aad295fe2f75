"""Links held by a process of their own (the link keeper), so that no drone flies on when the
flight loop's process dies or hangs.

The keeper is a small child process: it opens the cflib links (CflibLink), forwards each setpoint
the loop sends through a pipe, keeps cflib's pings and threads (they no longer share the loop's
GIL) and reports every link's figures back. It stops every flying drone (zero setpoint, STOP
setpoint, disarm) the moment

- the pipe closes (the loop's process exited or was killed, even by ``kill -9``: the kernel closes
  its end), or
- no message came for ``heartbeat_s`` while a drone flies on the loop's setpoints (a hung loop;
  the loop's own ``loop_overrun`` rule stops every drone at the same lateness; a drone the
  firmware's high-level commander flies, e.g. the hover before a race or a landing, holds itself
  and is not stopped for a silence), or
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
every REPORT_S and on every change of connection or stop). The loop's end of the pipe:
cfrace.flight.link.keeper_client (LinkKeeper, KeptLink).
"""

from __future__ import annotations

import json
import os
import signal
import struct
import sys
import threading
import time
from multiprocessing.connection import Connection

from cfrace.errors import LinkError
from cfrace.flight.loop.realtime import set_fifo

REPORT_S = 0.05            #: s between link figure reports (keeper -> loop)
ESTOP_FEED_S = 0.1         #: s between feeds of a flying drone's emergency-stop watchdog (the firmware's: 1 s)
SPAWN_TIMEOUT_S = 20.0     #: s for the keeper to start (it imports cflib)
CLOSE_S = 2.0              #: s the keeper waits for its links to close before it ends
SETPOINT_MSG = struct.Struct("<cBfffH")    #: b"s", drone, p, q, r (deg/s), thrust counts
POSE_MSG = struct.Struct("<cB7f")          #: b"p", drone, x, y, z (m), qw, qx, qy, qz


class _Keeper:
    """The child's state: its links, which drones fly, when the loop was last heard."""

    def __init__(self, conn, uris: list[str], heartbeat_s: float, stop_log: str | None, rt_priority: int = 0,
                 estop_watchdog: bool = False):
        from cfrace.flight.link.crazyflie import CflibLink   # cflib only in the keeper

        self.conn, self.heartbeat_s = conn, float(heartbeat_s)
        self.links = [CflibLink(u) for u in uris]
        self.flying = [False] * len(uris)
        self.streaming = [False] * len(uris)  #: flying on the loop's setpoints (not the high-level commander)
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
        self.streaming[i] = False
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
                set_fifo(self.rt_priority)   # the machine's ordinary jobs (cfrace.flight.loop.realtime)
                self.rt_priority = 0
            _, i, p, q, r, counts = SETPOINT_MSG.unpack(msg)
            if not self.dead[i]:
                self.links[i].send(p, q, r, counts)
                self.flying[i] = self.streaming[i] = True
        elif kind == b"p":
            _, i, *v = POSE_MSG.unpack(msg)
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
                self.streaming[i] = False   # the firmware flies it now (a notify-stop hands it over)
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
            if any(self.streaming):
                wait = min(wait, self.heartbeat_s - (now - self.last_heard))
            if any(self.flying):
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
            elif any(self.streaming) and now - self.last_heard > self.heartbeat_s:
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


if __name__ == "__main__":
    _opts = json.loads(sys.argv[2])
    keeper_main(Connection(int(sys.argv[1])), _opts["uris"], _opts["heartbeat_s"], _opts["stop_log"],
                _opts["rt_priority"], _opts["cpus"], _opts.get("estop_watchdog", False))
