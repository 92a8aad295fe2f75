"""The firmware's setpoint and its cascaded PID controller (position -> velocity -> attitude ->
rate), as the Crazyflie firmware's controller_pid.c, position_controller_pid.c and
attitude_pid_controller.c describe them. The last stage, the body-rate PID, is the simulator's own
(the drone profile's pid_roll_pitch / pid_yaw), so rates leave this module as the simulator's input.

Rules kept from the firmware:

* per axis a mode: disabled, absolute or velocity (setpoint_t's modeDisable/modeAbs/modeVelocity);
* x, y, z not disabled: the position controller (absolute axes: P-I-D on position error, output a
  velocity clamped to ``xVelMax/yVelMax * 1.1`` and ``max(zVelMax, 0.5) * 1.1``; x and y are run in
  the yaw-rotated body frame), then the velocity controller (vx, vy -> pitch, roll in deg clamped to
  ``pLimit/rLimit``; vz -> thrust = ``1000 * PID + thrustBase``, at least ``thrustMin``);
* x or y disabled: roll and pitch from the setpoint; z disabled: the setpoint's thrust;
* roll, pitch, yaw absolute: the attitude PID (error deg -> rate deg/s, integral limits 20, 20,
  360 deg s); roll or pitch in velocity mode: the setpoint's rate, attitude integrators reset;
* thrust 0 with z disabled: motors off and every integrator reset.

Simplified: one update rate (the fleet's 10 ms control period) for every stage; yaw in velocity mode
is passed to the rate loop as a body rate (the firmware integrates it into a yaw angle setpoint);
no velocity or acceleration feed-forward: with x, y, z absolute the position PID's output replaces
the setpoint's velocity and the acceleration is not used, as in position_controller_pid.c
(positionController; its feed-forward gains kff are 0 by default). The Mellinger controller
(simcf/mellinger.py, stabilizer.controller 2) uses them.
Angles here are right-handed (pitch positive = nose down), SI units; the firmware's legacy pitch
sign is applied where packets are decoded and logs written.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

DISABLE, ABS, VELOCITY = 0, 1, 2      #: setpoint modes (the firmware's modeDisable, modeAbs, modeVelocity)
RATE_LIMIT = math.radians(720.0)      #: rad/s, clamp of the attitude loop's rate output
THRUST_SCALE = 1000.0                 #: counts per unit of the vz PID output (firmware thrustScale)
LIMIT_OVERHEAD = 1.10                 #: the firmware's rpLimitOverhead and velMaxOverhead
MAX_COUNTS = 65535.0


@dataclass
class Setpoint:
    """One setpoint (the firmware's setpoint_t) in right-handed SI terms."""

    mode_x: int = DISABLE
    mode_y: int = DISABLE
    mode_z: int = DISABLE
    mode_roll: int = DISABLE
    mode_pitch: int = DISABLE
    mode_yaw: int = DISABLE
    position: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: m, world
    velocity: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: m/s, world (or body-yaw frame)
    velocity_body: bool = False        #: velocity x, y in the yaw-rotated body frame (hover setpoints)
    acceleration: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: m/s^2, world (the Mellinger controller's)
    attitude: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: rad, roll, pitch (nose down +), yaw
    rates: np.ndarray = field(default_factory=lambda: np.zeros(3))      #: rad/s, body p, q, r
    thrust: float = 0.0                #: counts, used when mode_z is DISABLE
    source: str = "stop"               #: what set it: legacy, generic type name, high-level, stop

    @property
    def is_stop(self) -> bool:
        return self.mode_z == DISABLE and self.thrust <= 0.0


class Pid:
    """The firmware's PID (pid.c without its filters): output = kp e + ki integral(e) + kd de/dt,
    the integral clamped to +-i_limit, the output to +-output_limit (0: none). The first update after
    a reset has no derivative term (no kick from the error jumping from 0)."""

    def __init__(self, i_limit: float):
        self.i_limit = i_limit
        self.integ = 0.0
        self.prev_error = None

    def reset(self) -> None:
        self.integ = 0.0
        self.prev_error = None

    def update(self, error: float, gains: tuple[float, float, float], dt: float, output_limit: float = 0.0) -> float:
        kp, ki, kd = gains
        self.integ = max(-self.i_limit, min(self.i_limit, self.integ + error * dt))
        deriv = (error - self.prev_error) / dt if dt > 0.0 and self.prev_error is not None else 0.0
        self.prev_error = error
        out = kp * error + ki * self.integ + kd * deriv
        if output_limit > 0.0:
            out = max(-output_limit, min(output_limit, out))
        return out


def _gains(p: dict, group: str, names: tuple[str, str, str]) -> tuple[float, float, float]:
    return tuple(float(p[f"{group}.{n}"]) for n in names)


def _wrap_deg(a: float) -> float:
    return (a + 180.0) % 360.0 - 180.0


class PidController:
    """The cascade for one drone. ``update`` -> (thrust counts, body rates rad/s (3,)); ``debug``
    holds the values the firmware logs (controller.*, posCtl.*)."""

    def __init__(self, attitude_i_limits=(20.0, 20.0, 360.0), pid_i_limit: float = 5000.0):
        self.pos_pid = [Pid(pid_i_limit) for _ in range(3)]
        self.vel_pid = [Pid(pid_i_limit) for _ in range(3)]
        self.att_pid = [Pid(lim) for lim in attitude_i_limits]
        self.debug: dict = {}

    def reset(self) -> None:
        for pid in self.pos_pid + self.vel_pid + self.att_pid:
            pid.reset()
        self.debug = {}

    def update(self, sp: Setpoint, pos: np.ndarray, vel: np.ndarray, euler: tuple[float, float, float],
               params: dict, dt: float) -> tuple[float, np.ndarray]:
        """sp: the setpoint; pos, vel: estimated (3,) world; euler: estimated roll, pitch, yaw rad
        (right-handed); params: the drone's parameters; dt: s since the last update."""
        if sp.is_stop:
            self.reset()
            return 0.0, np.zeros(3)
        roll, pitch, yaw = (math.degrees(a) for a in euler)
        att_des = np.degrees(sp.attitude)                       # deg, roll, pitch (nose down +), yaw
        thrust = float(sp.thrust)
        positional = not (sp.mode_x == DISABLE and sp.mode_y == DISABLE and sp.mode_z == DISABLE)
        if positional:
            t_cmd, r_des, p_des = self._position(sp, pos, vel, math.radians(yaw), params, dt)
            if sp.mode_z != DISABLE:
                thrust = t_cmd
            if sp.mode_x != DISABLE and sp.mode_y != DISABLE:
                att_des[0], att_des[1] = r_des, p_des
        else:
            for pid in self.pos_pid + self.vel_pid:
                pid.reset()
        rates = np.array(sp.rates, np.float64)                  # rad/s, the rate-mode axes as given
        rates_deg = np.degrees(rates)
        err = (att_des[0] - roll, att_des[1] - pitch, _wrap_deg(att_des[2] - yaw))
        modes = (sp.mode_roll, sp.mode_pitch, sp.mode_yaw)
        gains = [_gains(params, "pid_attitude", (f"{a}_kp", f"{a}_ki", f"{a}_kd")) for a in ("roll", "pitch", "yaw")]
        for k in range(3):
            angle_mode = modes[k] == ABS or (k < 2 and positional and sp.mode_x != DISABLE and sp.mode_y != DISABLE)
            if angle_mode:
                rates_deg[k] = self.att_pid[k].update(err[k], gains[k], dt, math.degrees(RATE_LIMIT))
                rates[k] = math.radians(rates_deg[k])
            else:
                self.att_pid[k].reset()
        self.debug.update({"cmd_thrust": thrust, "roll": att_des[0], "pitch": att_des[1], "yaw": att_des[2],
                           "rollRate": rates_deg[0], "pitchRate": rates_deg[1], "yawRate": rates_deg[2]})
        return thrust, rates

    def _position(self, sp: Setpoint, pos, vel, yaw: float, params: dict, dt: float) -> tuple[float, float, float]:
        """Position and velocity controllers -> (thrust counts, roll deg, pitch deg), right-handed."""
        c, s = math.cos(yaw), math.sin(yaw)
        body = lambda v: np.array([c * v[0] + s * v[1], -s * v[0] + c * v[1], v[2]])  # noqa: E731
        pos_b, vel_b, sp_pos_b = body(pos), body(vel), body(sp.position)
        v_sp = np.array(sp.velocity, np.float64) if sp.velocity_body else body(sp.velocity)
        vmax = (params["posCtlPid.xVelMax"] * LIMIT_OVERHEAD, params["posCtlPid.yVelMax"] * LIMIT_OVERHEAD,
                max(params["posCtlPid.zVelMax"], 0.5) * LIMIT_OVERHEAD)
        for k, (axis, mode) in enumerate(zip("xyz", (sp.mode_x, sp.mode_y, sp.mode_z))):
            if mode == ABS:
                g = _gains(params, "posCtlPid", (f"{axis}Kp", f"{axis}Ki", f"{axis}Kd"))
                v_sp[k] = self.pos_pid[k].update(sp_pos_b[k] - pos_b[k], g, dt, vmax[k])
            else:
                self.pos_pid[k].reset()
        r_lim, p_lim = params["posCtlPid.rLimit"], params["posCtlPid.pLimit"]
        out = []
        for k, axis in enumerate(("vx", "vy", "vz")):
            g = _gains(params, "velCtlPid", (f"{axis}Kp", f"{axis}Ki", f"{axis}Kd"))
            lim = (p_lim * LIMIT_OVERHEAD, r_lim * LIMIT_OVERHEAD, MAX_COUNTS / 2.0 / THRUST_SCALE)[k]
            out.append(self.vel_pid[k].update(v_sp[k] - vel_b[k], g, dt, lim))
        pitch = max(-p_lim, min(p_lim, out[0]))    # +vx error: nose down (right-handed +pitch)
        roll = max(-r_lim, min(r_lim, -out[1]))    # +vy error: roll left (right-handed -roll)
        thrust = max(float(params["posCtlPid.thrustMin"]), out[2] * THRUST_SCALE + params["posCtlPid.thrustBase"])
        thrust = min(thrust, MAX_COUNTS)
        self.debug.update({"targetVX": v_sp[0], "targetVY": v_sp[1], "targetVZ": v_sp[2],
                           "targetX": sp_pos_b[0], "targetY": sp_pos_b[1], "targetZ": sp.position[2]})
        return thrust, roll, pitch
