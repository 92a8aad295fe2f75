"""CflibLink: the real Crazyflie link through cflib (radio:// and udp://).

This and cfrace/calibrate/stand_link.py (the stand's log API) are the only modules of cfrace that import
cflib (GPL-3.0; we call it, we never copy it).
One Crazyflie object per drone; one Crazyradio per drone is the documented setup (two drones
at 100 Hz are ~220-420 packets/s, too many for one radio; docs/flight.md).

Link loss is detected three ways, whichever comes first: cflib's connection_lost / disconnected
callbacks (radio: too many lost packets; udp: socket errors), and silence: the drone is pinged
every 100 ms by cflib's link statistics (in the link keeper's process, cfrace.flight.link.keeper:
its threads do not share the flight loop's GIL), so ``quality.last_rx`` older than safety.link_timeout_s means the drone no
longer answers.
"""

from __future__ import annotations

import logging
import threading
import time
import warnings

from cfrace.errors import LinkError
from cfrace.flight.link.protocol import RATE_MODE_PARAMS, LinkQuality, cflib_setpoint_args, send_high_level

import cflib.crtp  # noqa: E402  (the one place cflib is imported)
from cflib.crazyflie import Crazyflie  # noqa: E402

_log = logging.getLogger("cflib")
_log.addHandler(logging.NullHandler())
_log.propagate = False   # cflib logs tracebacks for expected failures; we report one line ourselves

_drivers_ready = False
_drivers_lock = threading.Lock()
LOCK_READS = 3      #: supervisor state requests before a drone that does not answer passes
LOCKED_BIT = 6   #: the supervisor state bit "is locked": the firmware must be restarted (cflib Supervisor.STATES)


def _init_drivers() -> None:
    global _drivers_ready
    with _drivers_lock:
        if not _drivers_ready:
            cflib.crtp.init_drivers()
            _drivers_ready = True


def _reason(uri: str, message: str) -> str:
    """cflib's multi-line failure text -> one clear line."""
    text = " ".join(message.split())
    if "Cannot find a Crazyradio" in text:
        return f"{uri}: no Crazyradio found (plug in one Crazyradio PA per drone)"
    if "Connection refused" in text:
        return f"{uri}: nothing listens there (connection refused)"
    if "No driver found" in text or "malformed" in text.lower():
        return f"{uri}: malformed URI or no cflib driver for it"
    first = message.strip().splitlines()[0] if message.strip() else "unknown error"
    return f"{uri}: link failed ({first[:160]})"


class CflibLink:
    """A Link (cfrace.flight.link.protocol) to one real or simulated Crazyflie through cflib."""

    def __init__(self, uri: str):
        self.uri = uri
        self.quality = LinkQuality()
        self._cf: Crazyflie | None = None
        self._ready = threading.Event()
        self._failed: str | None = None
        self._params: dict[str, threading.Event] = {}
        self._vbat_log = None                    #: the pm.vbat log block, once started
        self._vbat_seen = threading.Event()

    # ------------------------------------------------------------------ callbacks (cflib threads)
    def _on_connected(self, uri):
        self.quality.connected = True
        self.quality.last_rx = time.monotonic()
        self._ready.set()

    def _on_failed(self, uri, message):
        self._failed = message
        self._ready.set()

    def _note_error(self, text: str) -> None:
        """Count a link error and keep its text (one line, 200 characters) for the log and view."""
        self.quality.errors += 1
        self.quality.error = " ".join(str(text).split())[:200]

    def _on_lost(self, uri, message):
        self.quality.connected = False
        self._note_error(message)

    def _on_disconnected(self, uri):
        self.quality.connected = False

    def _on_packet(self, pk):
        self.quality.last_rx = time.monotonic()

    def _on_latency(self, ms):
        self.quality.latency_ms = float(ms)

    def _on_link_quality(self, pct):
        self.quality.link_quality = float(pct)

    # ------------------------------------------------------------------ Link protocol
    def connect(self, timeout_s: float = 5.0) -> None:
        _init_drivers()
        cf = Crazyflie(rw_cache=None)
        cf.fully_connected.add_callback(self._on_connected)
        cf.connection_failed.add_callback(self._on_failed)
        cf.connection_lost.add_callback(self._on_lost)
        cf.disconnected.add_callback(self._on_disconnected)
        cf.packet_received.add_callback(self._on_packet)
        cf.link_statistics.latency_updated.add_callback(self._on_latency)
        cf.link_statistics.link_quality_updated.add_callback(self._on_link_quality)
        self._cf = cf
        self._ready.clear()
        self._failed = None
        cf.open_link(self.uri)
        answered = self._ready.wait(timeout_s)
        if self._failed is not None or not answered:
            self._shutdown()
            if self._failed is not None:
                raise LinkError(_reason(self.uri, self._failed))
            raise LinkError(f"{self.uri}: no answer within {timeout_s:g} s")

    def _param_cb(self, name, value):
        ev = self._params.get(name)
        try:
            if ev is not None and float(value) == 0.0:
                ev.set()
        except (TypeError, ValueError):
            pass

    def refuse_locked(self, why: str, then: str, close: bool = False) -> None:
        """LinkError (with ``close``: the link closed first) if the supervisor reports the drone locked by
        an emergency stop (bit LOCKED_BIT of supervisor.info; it ignores every command until rebooted). A reply of 0
        is no reply (a drone that answers has some state bit set) or legacy firmware: read again, up to
        LOCK_READS times."""
        cf = self._need()
        bits = 0
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # legacy firmware: no supervisor state (reads 0)
            for _ in range(LOCK_READS):
                bits = int(cf.supervisor.read_bitfield() or 0)
                if bits:
                    break
        if bits >> LOCKED_BIT & 1:
            if close:
                self._shutdown()
            raise LinkError(f"{self.uri}: the drone is locked by an emergency stop ({why}): {then}")

    def setup(self) -> None:
        """Refuse a drone the firmware has locked (an emergency stop: reboot required); rate mode for
        roll and pitch (confirmed by the drone), arming, zero-thrust unlock."""
        cf = self._need()
        self.refuse_locked("e.g. its emergency-stop watchdog after the last flight with --estop-watchdog",
                           "restart it (power cycle) first")
        for name in RATE_MODE_PARAMS:
            group, _, pname = name.partition(".")
            self._params[name] = threading.Event()
            cf.param.add_update_callback(group=group, name=pname, cb=self._param_cb)
            try:
                cf.param.set_value(name, 0)
            except (KeyError, AttributeError, Exception) as exc:  # cflib raises KeyError/plain Exception
                raise LinkError(f"{self.uri}: cannot set {name} = 0 ({exc})") from None
        for name in RATE_MODE_PARAMS:
            if not self._params[name].wait(2.0):
                raise LinkError(f"{self.uri}: the drone did not confirm {name} = 0 (rate mode) within 2 s")
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")   # legacy firmware: cflib falls back and warns
            cf.supervisor.send_arming_request(True)
        cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)   # a zero-thrust setpoint unlocks the motors
        self._start_battery_log()

    def _start_battery_log(self) -> None:
        """pm.vbat at 10 Hz into quality.vbat (the low-battery failsafe); once per connection, and
        not at all if the drone logs no pm.vbat."""
        cf = self._cf
        if cf is None or self._vbat_log is not None:
            return
        from cflib.crazyflie.log import LogConfig

        def got(ts, data, conf):
            self.quality.vbat = float(data["pm.vbat"])
            self._vbat_seen.set()
        conf = LogConfig(name="cfrace_battery", period_in_ms=100)
        try:
            conf.add_variable("pm.vbat", "float")
            cf.log.add_config(conf)
            conf.data_received_cb.add_callback(got)
            conf.start()
            self._vbat_log = conf
        except (KeyError, AttributeError) as exc:
            self._note_error(f"no pm.vbat log: {exc}")

    def _need(self) -> Crazyflie:
        if self._cf is None or not self.quality.connected:
            raise LinkError(f"{self.uri}: not connected")
        return self._cf

    def send(self, roll_rate_dps, pitch_rate_dps, yaw_rate_dps, thrust_counts) -> None:
        cf = self._cf
        if cf is None or cf.link is None:
            return
        r, p, y = cflib_setpoint_args(float(roll_rate_dps), float(pitch_rate_dps), float(yaw_rate_dps))
        cf.commander.send_setpoint(r, p, y, int(thrust_counts))
        self.quality.sent += 1

    def stop(self) -> None:
        """Zero thrust, the generic STOP setpoint (motors off), then disarm. Never raises."""
        cf = self._cf
        if cf is None or cf.link is None:
            return
        try:
            cf.commander.send_setpoint(0.0, 0.0, 0.0, 0)
            cf.commander.send_stop_setpoint()
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cf.supervisor.send_arming_request(False)
        except Exception as exc:  # a dying link must not stop us from stopping the others
            self._note_error(f"stop failed: {exc}")

    def close(self) -> None:
        self.stop()
        self._shutdown()

    def feed_estop_watchdog(self) -> None:
        """Feed the firmware's emergency-stop watchdog (localization port, EMERGENCY_STOP_WATCHDOG):
        once fed, the drone cuts its motors (and locks until rebooted) if 1 s passes without a feed.
        Never raises."""
        cf = self._cf
        if cf is None or cf.link is None:
            return
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cf.supervisor.send_emergency_stop_watchdog()
        except Exception as exc:  # a dying link: the silence check reports it
            self._note_error(f"emergency-stop watchdog feed failed: {exc}")

    # ------------------------------------------------------------------ the firmware's flight modes
    def send_pose(self, pos, quat) -> None:
        """The mocap pose as external pose (localization port): x y z, qx qy qz qw. Never raises."""
        cf = self._cf
        if cf is None or cf.link is None:
            return
        try:
            w, x, y, z = (float(v) for v in quat)
            cf.extpos.send_extpose(float(pos[0]), float(pos[1]), float(pos[2]), x, y, z, w)
        except Exception as exc:  # a dying link: the silence check reports it
            self._note_error(f"send_pose failed: {exc}")

    def high_level(self, command: str, **args) -> None:
        cf = self._cf
        if cf is None or cf.link is None:
            return
        try:
            send_high_level(cf.high_level_commander, command, args)
        except Exception as exc:
            self._note_error(f"high-level {command} failed: {exc}")

    def notify_stop(self) -> None:
        cf = self._cf
        if cf is None or cf.link is None:
            return
        try:
            cf.commander.send_notify_setpoint_stop()
        except Exception as exc:
            self._note_error(f"notify_stop failed: {exc}")

    def read_status(self, timeout_s: float = 2.0) -> dict:
        """The CRTP protocol version and the battery (nan if the drone logs no pm.vbat in time)."""
        cf = self._need()
        self._start_battery_log()
        self._vbat_seen.wait(timeout_s)
        return {"protocol": int(cf.platform.get_protocol_version()), "vbat": self.quality.vbat}

    def _shutdown(self) -> None:
        cf, self._cf = self._cf, None
        self._vbat_log = None
        self.quality.connected = False
        if cf is not None:
            try:
                # stop cflib's ping thread first: close_link() sets cf.link = None while that thread
                # may be inside send_packet (an AttributeError in a cflib thread otherwise)
                cf.link_statistics.stop()
            except Exception:
                pass
            try:
                cf.close_link()
            except Exception:
                pass
