"""UDP front end: one socket per simulated Crazyflie on 127.0.0.1, the way cflib's UDP driver talks.

Threads: one receiver (a selector over all drone sockets and the pose socket) answering each
datagram at once, and one clock thread that every ``tick`` s advances the fleet by the wall-clock
time elapsed (``realtime=True``), sends due log packets and console lines, and publishes poses.
With ``realtime=False`` the caller advances ``fleet`` itself (lockstep); the clock thread then
only sends log data, console lines and poses.
"""

from __future__ import annotations

import logging
import selectors
import signal
import socket
import threading
import time

from cfrace.drone import DEFAULT_PROFILE
from cfrace.errors import ConfigError, LinkError
from cfrace.simcf.crtp import CrtpEndpoint
from cfrace.simcf.firmware import SimFleet
from cfrace.simcf.poses import SUBSCRIPTION_TTL, encode_frame

log = logging.getLogger(__name__)
ERROR_LOG_EVERY_S = 1.0    #: s, bad packets are reported at most this often (one line each)

LOOPBACK = ("127.0.0.1", "localhost")
MAX_CATCH_UP = 0.1   #: s, the most simulated time one clock tick may add (beyond it the sim lags)
FLIGHT_OVER_S = 1.0  #: s without a datagram from any client (motors off) that ends a flight (reset_after_flight)


class SimCrazyflieServer:
    """Serve ``fleet``'s drones on udp://127.0.0.1:base_port+i (base_port 0: free ports)."""

    def __init__(self, fleet: SimFleet, base_port: int = 19850, host: str = "127.0.0.1", realtime: bool = True,
                 tick: float = 0.01, pose_port: int | None = None, reset_after_flight: bool = False,
                 on_reset=None):
        if host not in LOOPBACK:
            raise ConfigError(f"simcf: host {host!r} refused, the simulated drones listen on 127.0.0.1 only")
        if not 0 <= base_port <= 65535 - fleet.n:
            raise ConfigError(f"port (--port): base port {base_port} out of range 0..{65535 - fleet.n} "
                              f"(drone i listens on the base port + i; 0 picks free ports)")
        self.fleet = fleet
        self.host = "127.0.0.1"
        self.base_port = int(base_port)
        self._pose_port_given = pose_port is not None
        self.pose_port_requested = (self.base_port - 1 if self.base_port else 0) if pose_port is None else int(pose_port)
        self.realtime = bool(realtime)
        self.tick = float(tick)
        self.endpoints = [CrtpEndpoint(fleet, i) for i in range(fleet.n)]
        self._socks: list[socket.socket] = []
        self._pose_sock: socket.socket | None = None
        self._peers: list[tuple | None] = [None] * fleet.n
        self._subscribers: dict[tuple, float] = {}
        self._stop = threading.Event()
        self._threads: list[threading.Thread] = []
        self.ports: list[int] = []
        self._last_error_log = -ERROR_LOG_EVERY_S
        self.pose_port: int | None = None
        self.overruns = 0          #: clock ticks that had to drop time (simulation slower than real time)
        self.sim_lag = 0.0         #: s of wall-clock time not simulated because of overruns
        self.errors = 0            #: exceptions while handling a packet (logged)
        #: put the drones back on the start grid after each flight (see _after_flight); on_reset()
        #: is called each time
        self.reset_after_flight, self.on_reset = bool(reset_after_flight), on_reset
        self.resets = 0
        self._flown = False        #: a drone was armed since the start or the last reset
        self._last_rx = time.monotonic()

    # ------------------------------------------------------------------ lifecycle
    @property
    def uris(self) -> list[str]:
        return [f"udp://{self.host}:{p}" for p in self.ports]

    def start(self) -> "SimCrazyflieServer":
        if self._threads:
            return self
        try:
            for i in range(self.fleet.n):
                port = self.base_port + i if self.base_port else 0
                self._socks.append(self._bind(port, f"drone {self.fleet.body_names[i]}'s port"))
            self._pose_sock = self._bind(self.pose_port_requested, self._pose_port_words())
        except LinkError:
            self._close_sockets()
            raise
        self.ports = [s.getsockname()[1] for s in self._socks]
        self.pose_port = self._pose_sock.getsockname()[1]
        self._stop.clear()
        self._threads = [threading.Thread(target=self._rx_loop, name="simcf-rx", daemon=True),
                         threading.Thread(target=self._clock_loop, name="simcf-clock", daemon=True)]
        for t in self._threads:
            t.start()
        return self

    def _pose_port_words(self) -> str:
        if self._pose_port_given or not self.base_port:
            return "the ground-truth pose port"
        return f"the ground-truth pose port, the first drone's port {self.base_port} - 1"

    def _bind(self, port: int, what: str) -> socket.socket:
        sock = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
        try:
            sock.bind((self.host, port))
        except OSError as e:
            sock.close()
            raise LinkError(f"simcf: cannot listen on udp://{self.host}:{port} ({what}): {e.strerror or e}") from None
        sock.setblocking(False)
        return sock

    def stop(self) -> None:
        self._stop.set()
        for t in self._threads:
            t.join(timeout=2.0)
        self._threads = []
        self._close_sockets()

    def _close_sockets(self) -> None:
        for s in self._socks + ([self._pose_sock] if self._pose_sock else []):
            s.close()
        self._socks, self._pose_sock = [], None

    def __enter__(self) -> "SimCrazyflieServer":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    # ------------------------------------------------------------------ outputs
    def poses(self) -> tuple[float, dict]:
        """(t_sim s, {body: (pos, quat wxyz)}), thread-safe."""
        return self.fleet.poses()

    def lag_warning(self) -> str:
        """The line saying how far the simulation fell behind real time, or "" for less than one clock
        tick (a lag that would print as 0.00 s is no news)."""
        if self.sim_lag < self.tick:
            return ""
        return f"  warning: simulation fell behind real time by {self.sim_lag:.2f} s"

    def stats(self) -> list[dict]:
        """Per drone: datagrams received / sent, legacy setpoints received, client address."""
        return [{"uri": u, "rx": e.rx, "tx": e.tx, "setpoints": e.setpoints, "client": p}
                for u, e, p in zip(self.uris, self.endpoints, self._peers)]

    # ------------------------------------------------------------------ threads
    def _rx_loop(self) -> None:
        sel = selectors.DefaultSelector()
        for i, s in enumerate(self._socks):
            sel.register(s, selectors.EVENT_READ, i)
        sel.register(self._pose_sock, selectors.EVENT_READ, -1)
        try:
            while not self._stop.is_set():
                for key, _ in sel.select(timeout=0.1):
                    self._drain(key.fileobj, key.data)
        finally:
            sel.close()

    def _drain(self, sock: socket.socket, i: int) -> None:
        while True:
            try:
                data, addr = sock.recvfrom(256)
            except (BlockingIOError, InterruptedError):
                return
            except OSError:
                return          # e.g. ICMP port unreachable from a client that went away
            if i < 0:
                self._subscribers[addr] = time.monotonic()
                continue
            self._peers[i] = addr
            self._last_rx = time.monotonic()
            try:
                replies = self.endpoints[i].handle(data)
            except Exception as exc:   # a bad packet must not kill the drone: one line, at most 1/s
                self.errors += 1
                now = time.monotonic()
                if now - self._last_error_log >= ERROR_LOG_EVERY_S:
                    self._last_error_log = now
                    log.warning("simcf: drone %d dropped a bad packet (%d bytes, header 0x%02x): %s "
                                "(%d bad packets so far)", i, len(data), data[0] if data else 0,
                                " ".join(str(exc).split())[:120], self.errors)
                continue
            self._send(i, replies)

    def _send(self, i: int, datagrams: list[bytes]) -> None:
        addr = self._peers[i]
        if addr is None or not datagrams:
            return
        for d in datagrams:
            try:
                self._socks[i].sendto(d, addr)
            except OSError:
                return

    def _clock_loop(self) -> None:
        last = time.monotonic()
        next_tick = last + self.tick
        while not self._stop.is_set():
            now = time.monotonic()
            if self.realtime:
                elapsed = now - last
                if elapsed > MAX_CATCH_UP:
                    self.overruns += 1
                    self.sim_lag += elapsed - MAX_CATCH_UP
                    elapsed = MAX_CATCH_UP
                try:
                    self.fleet.advance(elapsed)
                except Exception:
                    self.errors += 1
                    log.exception("simcf: simulation step failed")
            last = now
            for i, e in enumerate(self.endpoints):
                try:
                    self._send(i, e.due_packets())
                except Exception:
                    self.errors += 1
                    log.exception("simcf: sending log data for drone %d failed", i)
            self._publish_poses(now)
            if self.reset_after_flight:
                self._after_flight(now)
            next_tick += self.tick
            delay = next_tick - time.monotonic()
            if delay < -self.tick:
                next_tick = time.monotonic() + self.tick
                delay = self.tick
            self._stop.wait(max(0.0, delay))

    def _after_flight(self, now: float) -> None:
        """Once a flight is over (a drone was armed; now every motor is off and no client has sent
        anything for FLIGHT_OVER_S), every drone back on the start grid, rebooted (SimFleet.reset)."""
        fleet = self.fleet
        with fleet.lock:
            status = [fleet.status(i) for i in range(fleet.n)]
            self._flown = self._flown or any(s["armed"] for s in status)
            if not self._flown or any(s["thrust"] > 0.0 for s in status) or now - self._last_rx < FLIGHT_OVER_S:
                return
            fleet.reset()
        self._flown = False
        self.resets += 1
        if self.on_reset is not None:
            self.on_reset()

    def _publish_poses(self, now: float) -> None:
        if not self._subscribers or self._pose_sock is None:
            return
        frame = encode_frame(*self.fleet.poses())
        for addr, seen in list(self._subscribers.items()):
            if now - seen > SUBSCRIPTION_TTL:
                self._subscribers.pop(addr, None)
                continue
            try:
                self._pose_sock.sendto(frame, addr)
            except OSError:
                self._subscribers.pop(addr, None)


def serve(track, drones: int, port: int = 19850, profile=DEFAULT_PROFILE, *, arming_required: bool = True,
          obstacles: bool = True, body_names=None, seed: int = 0, duration: float | None = None,
          decks=("lighthouse",), reset_after_flight: bool = False, out=print) -> list[dict]:
    """Run simulated Crazyflies until Ctrl-C / SIGTERM (or ``duration`` s). Prints the URIs via ``out``.
    The drones stay where each flight leaves them, as real drones do, unless ``reset_after_flight``
    (back on the start grid once a flight is over). Returns the per-drone packet statistics."""
    fleet = SimFleet(track, profile, drones, body_names=body_names, seed=seed,
                     arming_required=arming_required, obstacles=obstacles, decks=decks)
    server = SimCrazyflieServer(fleet, base_port=port, reset_after_flight=reset_after_flight,
                                on_reset=lambda: out("  flight over: every drone back on the start grid"))
    stop = threading.Event()
    restore = None
    if threading.current_thread() is threading.main_thread():
        restore = signal.signal(signal.SIGTERM, lambda *_: stop.set())
    try:
        with server:
            out(f"simulated Crazyflies ({fleet.profile.name}, track {fleet.track.name}, "
                f"{'arming required' if arming_required else 'auto-armed'}, "
                f"decks: {', '.join(fleet.decks) or 'none (external position only)'}):")
            for name, uri in zip(fleet.body_names, server.uris):
                out(f"  {name}: {uri}")
            out(f"  ground-truth poses: udp://127.0.0.1:{server.pose_port} (fly --mocap sim://127.0.0.1:{server.pose_port})")
            out("  after a flight: " + ("every drone back on the start grid (--reset-after-flight)" if reset_after_flight
                                        else "the drones stay where they landed, as real drones do; a ground start "
                                             "needs them on the grid (--reset-after-flight: put back)"))
            out("Ctrl-C to stop")
            t_end = None if duration is None else time.monotonic() + duration
            try:
                while not stop.is_set() and (t_end is None or time.monotonic() < t_end):
                    stop.wait(0.2 if t_end is None else max(0.0, min(0.2, t_end - time.monotonic())))
            except KeyboardInterrupt:
                pass
            stats = server.stats()
        for s in stats:
            out(f"  {s['uri']}: {s['rx']} packets in, {s['tx']} out, {s['setpoints']} setpoints")
        lag = server.lag_warning()
        if lag:
            out(lag)
        return stats
    finally:
        if restore is not None:
            signal.signal(signal.SIGTERM, restore)
