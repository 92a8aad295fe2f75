"""The supervisor's clocks of one simulated Crazyflie, as crazyflie-firmware's supervisor.c keeps them:

* isFlyingCheck: the drone "is flying" while some motor ran above idle within the last 2 s
  (IS_FLYING_HYSTERESIS_THRESHOLD), so the commander watchdog locks a drone that stopped its
  setpoints less than 1.5 s after its motors stopped (supervisor_state_machine.c: Flying ->
  WarningLevelOut -> ExceptFreeFall -> Locked).
* supervisorIsPreflightTimeout: armed and not flown for ``supervisor.prefltTimeout`` ms (30 s)
  -> disarmed (ReadyToFly -> PreFlChecksPassed).
* supervisorIsLandingTimeout: ``supervisor.landedTimeout`` ms (3 s) after it stopped flying -> the
  supervisor resets and disarms (Landed -> Reset).
* isTumbledCheck: the accelerometer's body z below 0.5 g (60 deg tilt) for 1 s, or below -0.2 g
  (upside down) for 0.1 s; free fall (every axis under 0.1 g) resets the clock; with
  ``supervisor.crashDetectGs`` above 0, a reading whose norm is further than that from 1 g counts
  as tumbled at once (crash_g). With ``supervisor.tmblChckEn`` set, a tumble while flying crashes
  the drone (supervisor_state_machine.c: Flying -> Crashed, motors off until a crash recovery
  request while no longer tumbled), before take-off it disarms.

The platforms without arming (Crazyflie 2.1) re-arm by themselves, so only the crash shows.

What the supervisor reads and how often (stabilizer.c, supervisorUpdate; stabilizer_types.h,
RATE_SUPERVISOR): it runs at 25 Hz, every 40th tick of the 1 kHz stabilizer loop, on the
accelerometer as the sensor driver leaves it (sensors_bmi088_bmp3xx.c: each axis through
filter.c's lpf2p, a 2nd-order Butterworth low-pass at 30 Hz on the 1 kHz samples,
ACCEL_LPF_CUTOFF_FREQ). ``AccelerometerFilter`` is that reading: a 10 ms knock between two drones
shows in it smoothed and a few ms late, and the supervisor sees it only if one of its ticks falls
on it, as on a real drone.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

IS_FLYING_HYSTERESIS = 2.0     #: s
TILT_ACC_Z = 0.5               #: g, body z below this is tilted (60 deg when stationary)
TILT_TIME = 1.0                #: s
UPSIDE_DOWN_ACC_Z = -0.2       #: g
UPSIDE_DOWN_TIME = 0.1         #: s
FREE_FALL_ACC = 0.1            #: g, every axis below this is free fall
SENSOR_RATE_HZ = 1000          #: the accelerometer's samples and the stabilizer loop's ticks
ACC_LPF_CUTOFF_HZ = 30.0       #: sensors_bmi088_bmp3xx.c, ACCEL_LPF_CUTOFF_FREQ
SUPERVISOR_TICKS = 40          #: stabilizer ticks (ms) between supervisor updates (RATE_SUPERVISOR, 25 Hz)


def _lpf2p_coefficients(sample_hz: float, cutoff_hz: float) -> tuple[float, float, float, float, float]:
    """(b0, b1, b2, a1, a2) of filter.c's lpf2pSetCutoffFreq: the bilinear 2nd-order Butterworth."""
    ohm = math.tan(math.pi * cutoff_hz / sample_hz)
    k = 2.0 * math.cos(math.pi / 4.0) * ohm
    c = 1.0 + k + ohm * ohm
    b0 = ohm * ohm / c
    return b0, 2.0 * b0, b0, 2.0 * (ohm * ohm - 1.0) / c, (1.0 - k + ohm * ohm) / c


_ACC_LPF = _lpf2p_coefficients(SENSOR_RATE_HZ, ACC_LPF_CUTOFF_HZ)


@dataclass
class AccelerometerFilter:
    """The firmware's accelerometer reading of one drone (body frame, g): each axis low-passed as
    filter.c's lpf2pApply does, one sample per ms. ``reading`` is the newest output."""

    delay: list | None = None      #: per axis [d1, d2]; None until the first sample
    reading: tuple = (0.0, 0.0, 1.0)

    def run(self, sample, ms: int, tap: int | None = None):
        """Feed the same sample (3,) for ms 1 kHz ticks; returns the reading after tick ``tap``
        (1..ms) when asked, else None. The first sample ever settles the filter on it (lpf2pReset:
        the sensors have run through the boot's calibration before anything reads them)."""
        b0, b1, b2, a1, a2 = _ACC_LPF
        x = [float(v) for v in sample]
        if self.delay is None:
            self.delay = [[v / (b0 + b1 + b2)] * 2 for v in x]
        out, tapped = list(self.reading), None
        for j in range(1, ms + 1):
            for k in range(3):
                d = self.delay[k]
                d0 = x[k] - d[0] * a1 - d[1] * a2
                out[k] = d0 * b0 + d[0] * b1 + d[1] * b2
                d[1], d[0] = d[0], d0
            if j == tap:
                tapped = tuple(out)
        self.reading = tuple(out)
        return tapped


def crash_g(acc_g, max_gs: float) -> float | None:
    """isTumbledCheck's crash detection (``supervisor.crashDetectGs``, 0 = off, the default): the
    accelerometer's norm (g) when it is more than max_gs from 1 g, else None."""
    norm = math.sqrt(sum(float(v) * float(v) for v in acc_g))
    return norm if max_gs > 0.0 and abs(norm - 1.0) > max_gs else None


def supervisor_tick(start_ms: int, ms: int) -> int | None:
    """Of the ticks start_ms+1 .. start_ms+ms, the offset (1..ms) of the one where supervisorUpdate
    runs (a multiple of SUPERVISOR_TICKS), or None."""
    j = SUPERVISOR_TICKS - start_ms % SUPERVISOR_TICKS
    return j if j <= ms else None


@dataclass
class SupervisorClock:
    """The supervisor's times of one drone (simulated s; None: not yet)."""

    latest_thrust: float | None = None     #: some motor above idle
    armed_at: float | None = None          #: latest arming
    tumble_since: float | None = None      #: first tilted sample of the current tumble

    def note_thrust(self, t: float, above_idle: bool) -> None:
        if above_idle:
            self.latest_thrust = t

    def is_flying(self, t: float) -> bool:
        return self.latest_thrust is not None and t - self.latest_thrust < IS_FLYING_HYSTERESIS

    def flown_since_arming(self) -> bool:
        return self.latest_thrust is not None and self.armed_at is not None and self.latest_thrust >= self.armed_at

    def preflight_timeout(self, t: float, armed: bool, timeout_ms: int) -> bool:
        """Armed (ReadyToFly) and not flown since, for longer than timeout_ms."""
        return (armed and self.armed_at is not None and not self.flown_since_arming()
                and t - self.armed_at > timeout_ms / 1000.0)

    def landing_timeout(self, t: float, armed: bool, timeout_ms: int) -> bool:
        """Flew since arming, stopped flying (Landed), and timeout_ms more passed."""
        return (armed and self.flown_since_arming() and not self.is_flying(t)
                and t - (self.latest_thrust + IS_FLYING_HYSTERESIS) > timeout_ms / 1000.0)

    def tumbled(self, t: float, acc_body_g) -> bool:
        """isTumbledCheck on one accelerometer sample (body frame, g)."""
        ax, ay, az = (float(v) for v in acc_body_g)
        if abs(ax) < FREE_FALL_ACC and abs(ay) < FREE_FALL_ACC and abs(az) < FREE_FALL_ACC:
            self.tumble_since = None
            return False
        if az >= TILT_ACC_Z:
            self.tumble_since = None
            return False
        if self.tumble_since is None:
            self.tumble_since = t
        held = t - self.tumble_since
        return (az < UPSIDE_DOWN_ACC_Z and held > UPSIDE_DOWN_TIME) or held > TILT_TIME
