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
  (upside down) for 0.1 s; free fall (every axis under 0.1 g) resets the clock. With
  ``supervisor.tmblChckEn`` set, a tumble while flying locks the drone, before take-off it disarms.

The platforms without arming (Crazyflie 2.1) re-arm by themselves, so only the tumble lock shows.
"""

from __future__ import annotations

from dataclasses import dataclass

IS_FLYING_HYSTERESIS = 2.0     #: s
TILT_ACC_Z = 0.5               #: g, body z below this is tilted (60 deg when stationary)
TILT_TIME = 1.0                #: s
UPSIDE_DOWN_ACC_Z = -0.2       #: g
UPSIDE_DOWN_TIME = 0.1         #: s
FREE_FALL_ACC = 0.1            #: g, every axis below this is free fall


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
