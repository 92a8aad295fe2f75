"""The Crazyflie on the stand, through cflib: the firmware's motor test parameters, the battery and
motor-speed log, arming and the emergency-stop watchdog.

Built on CflibLink (connection, link-loss detection, stop); cflib's log API is the one thing it
adds, and this is the one other module that imports cflib. Names and units as the firmware:
parameters motorPowerSet.enable (uint8: 0 off, 1 each motor its own value, 2 m1 to all) and
motorPowerSet.m1..m4 (uint16 counts); log variables pm.vbat (float, V) and, where the drone
measures motor speed, rpm.m1..m4 (uint16, revolutions per minute). A drone whose supervisor
reports "is locked" (bit 6 of supervisor.info, cflib Supervisor.is_locked: after an emergency stop
or its emergency-stop watchdog, i.e. after every stand run) ignores the override until rebooted.
"""

from __future__ import annotations

import threading
import time
import warnings

import numpy as np

from cfrace.errors import LinkError
from cfrace.flight.link.crazyflie import CflibLink

from cflib.crazyflie.log import LogConfig  # noqa: E402

MOTOR_PARAMS = ("motorPowerSet.enable", "motorPowerSet.m1", "motorPowerSet.m2", "motorPowerSet.m3",
                "motorPowerSet.m4")
#: motor speed logs, the first the drone has: the Brushless's ESC telemetry (bidirectional DShot), the RPM deck
RPM_SOURCES = (("motor.m1_rpm", "motor.m2_rpm", "motor.m3_rpm", "motor.m4_rpm"), ("rpm.m1", "rpm.m2", "rpm.m3", "rpm.m4"))


class StandLink(CflibLink):
    """CflibLink plus what the stand needs. ``log()`` returns (host t (m,), vbat (m,), rpm (m, 4) | None)."""

    def __init__(self, uri: str):
        super().__init__(uri)
        self.has_rpm = False
        self.rpm_vars: tuple = ()               #: the motor speed logs in use (RPM_SOURCES)
        self._log_lock = threading.Lock()
        self._log_rows: list[tuple] = []
        self._log_conf = None
        self.last_log: float | None = None      #: host time of the newest log packet

    def prepare(self, period_ms: int = 10) -> None:
        """Check the TOCs and that the drone is not locked, zero the motor override, start the battery /
        motor-speed log (arming is ``arm``, after the tare)."""
        cf = self._need()
        missing = [n for n in MOTOR_PARAMS if cf.param.toc.get_element_by_complete_name(n) is None]
        if missing:
            raise LinkError(f"{self.uri}: the firmware has no parameter {missing[0]} (the motor test override); "
                            "update the Crazyflie firmware")
        if cf.log.toc.get_element_by_complete_name("pm.vbat") is None:
            raise LinkError(f"{self.uri}: the firmware logs no pm.vbat")
        self.refuse_locked("e.g. its emergency-stop watchdog 1 s after the last stand run; its motors would not "
                           "spin", "power-cycle it (a simulated one: restart `cfrace sim stand`), then run again",
                           close=True)
        found = [vs for vs in RPM_SOURCES if all(cf.log.toc.get_element_by_complete_name(n) is not None for n in vs)]
        self.rpm_vars = found[0] if found else ()
        self.has_rpm = bool(found)
        self._params["motorPowerSet.enable"] = threading.Event()
        cf.param.add_update_callback(group="motorPowerSet", name="enable", cb=self._param_cb)
        self.set_motors(0, 0)
        conf = LogConfig(name="stand", period_in_ms=period_ms)
        conf.add_variable("pm.vbat", "float")
        if self.has_rpm:
            for n in self.rpm_vars:
                conf.add_variable(n, "uint16_t")
        conf.data_received_cb.add_callback(self._on_log)
        try:
            cf.log.add_config(conf)
            conf.start()
        except (KeyError, AttributeError) as exc:
            raise LinkError(f"{self.uri}: cannot start the stand log ({exc})") from None
        self._log_conf = conf
        self.feed_watchdog()

    def arm(self) -> None:
        """Arm (after the tare: an armed Crazyflie 2.1 Brushless spins its props at idle thrust)."""
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            self._need().supervisor.send_arming_request(True)

    def _on_log(self, timestamp, data, conf) -> None:
        now = time.monotonic()
        rpm = tuple(float(data[n]) for n in self.rpm_vars)
        with self._log_lock:
            self._log_rows.append((now, float(data["pm.vbat"])) + rpm)
            self.last_log = now

    def log(self) -> tuple[np.ndarray, np.ndarray, np.ndarray | None]:
        with self._log_lock:
            rows = np.array(self._log_rows, dtype=np.float64).reshape(len(self._log_rows), -1)
        if not len(rows):
            return np.zeros(0), np.zeros(0), (np.zeros((0, 4)) if self.has_rpm else None)
        return rows[:, 0], rows[:, 1], (rows[:, 2:6] if self.has_rpm else None)

    def latest_vbat(self) -> float | None:
        with self._log_lock:
            return self._log_rows[-1][1] if self._log_rows else None

    def set_motors(self, enable: int, counts) -> None:
        """enable 1: counts is (4,) per motor; 2: counts is one value for all (sent as m1); 0: off.
        Commands first, then the mode, so that switching a mode on never applies stale values."""
        cf = self._need()
        values = [int(c) for c in (counts if np.ndim(counts) else [counts, 0, 0, 0])]
        for k, v in enumerate(values):
            cf.param.set_value(f"motorPowerSet.m{k + 1}", max(0, min(65535, v)))
        cf.param.set_value("motorPowerSet.enable", int(enable))

    def set_m1(self, counts: int) -> None:
        """One write: the command of all motors in mode 2 (or of motor 1 in mode 1)."""
        self._need().param.set_value("motorPowerSet.m1", max(0, min(65535, int(counts))))

    def set_motor(self, motor: int, counts: int) -> None:
        self._need().param.set_value(f"motorPowerSet.m{motor + 1}", max(0, min(65535, int(counts))))

    def feed_watchdog(self) -> None:
        """The firmware stops the motors unless this comes again within 1 s (set up on first call)."""
        cf = self._cf
        if cf is not None and cf.link is not None:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                cf.supervisor.send_emergency_stop_watchdog()

    def motors_off(self, emergency: bool, confirm_s: float = 1.0) -> bool:
        """Stop the motors at once: the emergency stop packet first when asked (the drone then needs a
        reboot), then the override's commands to 0 and off (waiting up to confirm_s for the drone to
        confirm enable = 0), then the base stop (STOP setpoint, disarm). Returns whether the drone
        confirmed. Never raises: a dead link must not keep us from trying every way."""
        cf = self._cf
        if cf is None or cf.link is None:
            return False
        confirmed = self._params.setdefault("motorPowerSet.enable", threading.Event())
        confirmed.clear()
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                if emergency:
                    cf.supervisor.send_emergency_stop()
            for k in range(4):
                cf.param.set_value(f"motorPowerSet.m{k + 1}", 0)
            cf.param.set_value("motorPowerSet.enable", 0)
        except Exception as exc:   # noqa: BLE001 - stopping must go on
            self._note_error(f"motors_off failed: {exc}")
        ok = confirmed.wait(confirm_s)
        self.stop()
        return ok

    def close(self) -> None:
        if self._log_conf is not None:
            try:
                self._log_conf.stop()
            except Exception:   # noqa: BLE001
                pass
        super().close()
