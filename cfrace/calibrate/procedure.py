"""The stand procedure: tare, all four motors up and down, each motor up and down, the lag test;
rests between; safety checks every 10 ms; the motors are stopped on every way out.

Every change of command is a ramp at ``slew`` counts/s except the lag test's steps, which are the
point of that test and limited to ``max_step`` counts. The run stops (motors off at once, with the
emergency stop) on Ctrl-C, a CAN timeout (no sensor sample for the sensor's timeout_ms), a
reading beyond the sensor's range or saturated, a lost link (no packet from the drone for
``link_timeout_s``), or a battery below ``min_vbat``. The drone's own emergency-stop watchdog,
fed every 100 ms, stops the motors within 1 s if this program or its link dies.
"""

from __future__ import annotations

import datetime as _dt
import math
import time
from dataclasses import dataclass

import numpy as np

from cfrace.calibrate.bus import SensorReader, StandError, open_bus, parse_bus
from cfrace.calibrate.fit import Hold, Recording, Step
from cfrace.calibrate.sensor import SensorSpec
from cfrace.errors import ConfigError, LinkError

TICK = 0.01              #: s, period of the safety checks and ramps
WATCHDOG_FEED = 0.1      #: s between emergency-stop watchdog feeds


@dataclass(frozen=True)
class Plan:
    """What the stand does. Counts are the firmware's uint16 motor commands."""

    levels: tuple[int, ...] = (5000, 10000, 15000, 20000, 25000, 30000, 35000, 40000, 45000, 50000, 55000, 60000,
                               65535)
    motors: tuple[int, ...] = (0, 1, 2, 3)   #: motors measured alone (0-3 = M1-M4)
    hold_s: float = 0.6                      #: s at each level (the first settle_s not measured)
    settle_s: float = 0.25
    rest_s: float = 1.0                      #: s motors off between parts
    slew: float = 60000.0                    #: counts/s of every ramp
    tau_low: int = 24000                     #: lag test: steps between these commands (all motors)
    tau_high: int = 32000
    tau_repeats: int = 4                     #: up-and-down pairs
    tau_hold_s: float = 0.35
    max_step: int = 10000                    #: the largest unramped step (the lag test's)
    link_timeout_s: float = 0.5
    min_vbat: float = 3.2                    #: V, stop below

    def check(self) -> None:
        lv = list(self.levels)
        if not lv or any(b <= a for a, b in zip(lv, lv[1:])) or lv[0] <= 0 or lv[-1] > 65535:
            raise ConfigError(f"stand plan: levels must increase within 1..65535, got {lv}")
        if not set(self.motors) <= {0, 1, 2, 3} or not self.motors:
            raise ConfigError(f"stand plan: motors must be among 0-3 (M1-M4), got {list(self.motors)}")
        if not 0 < self.settle_s < self.hold_s:
            raise ConfigError(f"stand plan: need 0 < settle_s ({self.settle_s}) < hold_s ({self.hold_s})")
        if not 0 < self.tau_high - self.tau_low <= self.max_step or self.tau_low <= 0:
            raise ConfigError(f"stand plan: the lag test's step {self.tau_low} -> {self.tau_high} must be positive "
                              f"and at most max_step = {self.max_step} counts")
        if self.slew <= 0 or self.rest_s < 0 or self.tau_repeats < 1:
            raise ConfigError("stand plan: slew > 0, rest_s >= 0 and tau_repeats >= 1 required")

    def duration(self) -> float:
        """s, about (without connecting)."""
        sweep = (2 * len(self.levels) - 1) * self.hold_s + 2 * self.levels[-1] / self.slew
        return ((1 + len(self.motors)) * (sweep + self.rest_s) + 2 * self.tau_repeats * self.tau_hold_s
                + 2 * self.tau_low / self.slew + self.rest_s)


#: A short plan for tests and trying things out (seconds on the simulated stand).
QUICK_PLAN = Plan(levels=(20000, 42000, 65535), motors=(0, 1), hold_s=0.3, settle_s=0.12, rest_s=0.3, slew=250000.0,
                  tau_repeats=2, tau_hold_s=0.25)


class _Session:
    def __init__(self, link, reader: SensorReader, plan: Plan, out):
        self.link, self.reader, self.plan, self.out = link, reader, plan, out
        self.holds: list[Hold] = []
        self.steps: list[Step] = []
        self._fed = 0.0

    def wait(self, seconds: float) -> None:
        """Sleep in TICK slices, checking the sensor, the link and the battery; feeding the watchdog."""
        t_end = time.monotonic() + seconds
        while True:
            now = time.monotonic()
            self.check(now)
            if now - self._fed >= WATCHDOG_FEED:
                self.link.feed_watchdog()
                self._fed = now
            if now >= t_end:
                return
            time.sleep(min(TICK, t_end - now))

    def check(self, now: float) -> None:
        r, sensor = self.reader, self.reader.sensor
        if r.fault:
            raise StandError(r.fault)
        silent = r.silent_for()
        if silent is not None and silent > sensor.timeout_s:
            age = "since the start" if silent == math.inf else f"for {silent * 1e3:.0f} ms"
            raise StandError(f"{r.where}: CAN timeout, no sample from the sensor {age} "
                             f"(limit {sensor.timeout_s * 1e3:g} ms)")
        q = self.link.quality
        if not q.connected or q.last_rx is None or now - q.last_rx > self.plan.link_timeout_s:
            age = "" if q.last_rx is None else f" for {now - q.last_rx:.2f} s"
            raise LinkError(f"{self.link.uri}: link lost (no packet from the drone{age}); its emergency-stop "
                            "watchdog stops the motors within 1 s")
        v = self.link.latest_vbat()
        if v is not None and v < self.plan.min_vbat:
            raise StandError(f"{self.link.uri}: battery at {v:.2f} V, below {self.plan.min_vbat:g} V: charge it")

    def ramp(self, setter, start: int, end: int) -> None:
        n = max(1, math.ceil(abs(end - start) / self.plan.slew / TICK))
        for k in range(1, n + 1):
            setter(int(round(start + (end - start) * k / n)))
            self.wait(TICK)

    def hold(self, kind: str, motor: int | None, counts: int) -> None:
        t0 = time.monotonic() + self.plan.settle_s
        self.wait(self.plan.hold_s)
        self.holds.append(Hold(kind, motor, counts, t0, time.monotonic()))

    def sweep(self, kind: str, motor: int | None, setter) -> None:
        levels = list(self.plan.levels)
        cur = 0
        for c in levels + levels[-2::-1]:
            self.ramp(setter, cur, c)
            cur = c
            self.hold(kind, motor, c)
            _, _, w = self.reader.samples(max(0, self.reader.count() - 20))
            self.out(f"  {'all motors' if kind == 'all' else f'motor M{motor + 1}'} {c:5d} counts: "
                     f"{w[:, 2].mean():.4f} N, {w[:, 5].mean() * 1e3:+.3f} mN m yaw, "
                     f"{self.link.latest_vbat() or float('nan'):.3f} V")
        self.ramp(setter, cur, 0)

    def run(self) -> None:
        p = self.plan
        self.out("tare (motors off)")
        self.wait(self.reader.sensor.tare_samples / self.reader.sensor.rate_hz + 0.1)
        bias = self.reader.tare()
        self.out(f"  bias: force {np.round(bias[:3], 4).tolist()} N, torque {np.round(bias[3:] * 1e3, 3).tolist()} mN m")
        self.link.arm()        # after the tare: armed, a Brushless's props idle
        self.wait(0.1)
        self.out("all four motors, up and down")
        self.link.set_motors(2, 0)
        self.sweep("all", None, self.link.set_m1)
        self.link.set_motors(0, 0)
        self.wait(p.rest_s)
        for m in p.motors:
            self.out(f"motor M{m + 1} alone, up and down")
            self.link.set_motors(1, [0, 0, 0, 0])
            self.sweep("motor", m, lambda c, m=m: self.link.set_motor(m, c))
            self.link.set_motors(0, 0)
            self.wait(p.rest_s)
        self.out(f"lag test: {p.tau_repeats} x steps {p.tau_low} <-> {p.tau_high} counts, all motors")
        self.link.set_motors(2, 0)
        self.ramp(self.link.set_m1, 0, p.tau_low)
        self.wait(p.tau_hold_s)
        for _ in range(p.tau_repeats):
            for a, b in ((p.tau_low, p.tau_high), (p.tau_high, p.tau_low)):
                t = time.monotonic()
                self.link.set_m1(b)
                self.wait(p.tau_hold_s)
                self.steps.append(Step(t, a, b, time.monotonic()))
        self.ramp(self.link.set_m1, p.tau_low, 0)
        self.link.set_motors(0, 0)
        self.wait(p.rest_s)


def run_stand(uri: str, sensor: SensorSpec, bus: str, plan: Plan = Plan(), *, confirmed: bool = False,
              out=print, connect_timeout_s: float = 5.0) -> Recording:
    """Run the procedure on the Crazyflie at ``uri`` with the sensor on ``bus``; returns the recording.
    Raises StandError / LinkError / KeyboardInterrupt after stopping the motors."""
    from cfrace.calibrate.stand_link import StandLink

    if not confirmed:
        raise StandError("refusing to start the motors: fix the Crazyflie on the stand with its propellers on, "
                         "stand clear, then pass --confirm-secured")
    plan.check()
    spec = parse_bus(bus)
    can_bus = open_bus(spec)
    reader = SensorReader(can_bus, sensor, str(spec)).start()
    link = None
    clean = False
    try:
        reader.wait_samples(10, max(1.0, 20.0 / sensor.rate_hz))   # a silent bus fails before the drone is touched
        link = StandLink(uri)
        link.connect(connect_timeout_s)
        link.prepare()
        session = _Session(link, reader, plan, out)
        session.wait(0.3)      # first log packets
        started = _dt.datetime.now(_dt.timezone.utc)
        session.run()
        clean = True
    finally:
        if link is not None:
            confirmed_off = link.motors_off(emergency=not clean)
            if not confirmed_off and clean:
                out(f"warning: {uri} did not confirm motorPowerSet.enable = 0; check that the motors stopped")
            link.close()
        reader.stop()
        can_bus.shutdown()
    host, stime, wrench = reader.samples()
    log_t, vbat, rpm = link.log()
    info = {"date": started.date().isoformat(), "started_utc": started.isoformat(timespec="seconds"),
            "sensor": sensor.name, "bus": str(spec), "uri": uri, "bias": reader.bias.tolist(),
            "bad_frames": reader.bad_frames, "has_rpm": rpm is not None}
    return Recording(host, stime, wrench, log_t, vbat, rpm, session.holds, session.steps, info)
