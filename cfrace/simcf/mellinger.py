"""The firmware's Mellinger controller (stabilizer.controller 2), after crazyflie-firmware
src/modules/src/controller/controller_mellinger.c, controllerMellinger: a geometric tracking
controller that uses the whole setpoint the high-level commander sends (position, velocity,
acceleration, yaw and the body rates of the trajectory, crtp_commander_high_level.c
crtpCommanderHighLevelGetSetpoint), so it tracks a trajectory closely where the PID controller
(which turns the position error alone into a velocity, position_controller_pid.c) lags.

Rules kept from the firmware:

* x absolute: the desired force ``F = m a_sp + kp e_p + kd e_v + ki int(e_p)`` (xy and z gains of
  their own; z adds ``m g``; integrals clamped to ``i_range_xy``/``i_range_z``), its direction the
  desired body z axis, the desired x axis from the yaw setpoint (absolute; a yaw rate moves it from
  the estimated yaw); the collective thrust is F along the *estimated* body z axis, in counts
  ``massThrust * F``;
* roll and pitch absolute with z disabled (manual flight): the desired attitude from the setpoint's
  roll, pitch and yaw, the thrust the setpoint's;
* any other combination: hold the setpoint's z with the drone level and its yaw as it is;
* the attitude error ``eR = vee(Rd^T R - R^T Rd)`` (no factor 1/2, as the firmware's), the rate
  error against the setpoint's body rates, the yaw moment's integral (``ki_m_z``, ``i_range_m_z``);
* z disabled: the setpoint's thrust; no thrust: every integral reset.

Simplified: the firmware turns eR and the rate error into moments, ``M = -kR eR + kw (w_sp - w)
+ ki_m int(-eR)`` (plus a rate-derivative term ``kd_omega_rp``), and mixes them into the motors.
The simulated drone's last stage is the simulator's own body-rate PID, so the same law is written
as the rate command it implies, ``w_cmd = w_sp + (-kR eR + ki_m int(-eR)) / kw``, which that PID
tracks (its gains stand for kw and kd_omega_rp); rate commands are clamped to 720 deg/s. One update
per 10 ms control period (the firmware: 500 Hz). Right-handed SI throughout (the firmware's legacy
pitch sign is applied where packets are decoded and logs written).
"""

from __future__ import annotations

import math

import numpy as np

from cfrace.drone import GRAVITY
from cfrace.rotations import quat_to_rot
from cfrace.simcf.controller import ABS, DISABLE, MAX_COUNTS, RATE_LIMIT, VELOCITY, Setpoint
from cfrace.simcf.params import MELLINGER_GAINS


def _unit(v: np.ndarray) -> np.ndarray:
    n = float(np.linalg.norm(v))
    return v / n if n > 0.0 else v


def rpy_to_rot(roll: float, pitch: float, yaw: float) -> np.ndarray:
    """World-from-body rotation (3, 3) of ZYX Euler angles, rad (pitch + = nose down)."""
    cr, sr, cp, sp, cy, sy = math.cos(roll), math.sin(roll), math.cos(pitch), math.sin(pitch), math.cos(yaw), math.sin(yaw)
    return np.array([[cy * cp, cy * sp * sr - sy * cr, cy * sp * cr + sy * sr],
                     [sy * cp, sy * sp * sr + cy * cr, sy * sp * cr - cy * sr],
                     [-sp, cp * sr, cp * cr]])


def _axes_from(z_des: np.ndarray, yaw: float) -> np.ndarray:
    """Desired rotation (columns x, y, z body axes) with body z ``z_des`` and heading ``yaw`` rad."""
    x_c = np.array([math.cos(yaw), math.sin(yaw), 0.0])
    y_des = _unit(np.cross(z_des, x_c))
    return np.column_stack([np.cross(y_des, z_des), y_des, z_des])


class MellingerController:
    """One drone's Mellinger controller. ``update`` -> (thrust counts, body rates rad/s (3,)), the
    interface of `cfrace.simcf.controller.PidController`; ``debug`` holds the controller.* logs."""

    def __init__(self):
        self.reset()

    def reset(self) -> None:
        """controllerMellingerReset: every integral to zero."""
        self.i_pos = np.zeros(3)
        self.i_att = np.zeros(3)
        self.debug: dict = {}

    def update(self, sp: Setpoint, pos: np.ndarray, vel: np.ndarray, quat: np.ndarray, params: dict,
               dt: float) -> tuple[float, np.ndarray]:
        """sp: the setpoint; pos, vel: estimated (3,) world; quat: estimated attitude (wxyz, world from
        body); params: the drone's parameters (ctrlMel.*); dt: s since the last update."""
        if sp.is_stop:
            self.reset()
            return 0.0, np.zeros(3)
        g = {name: float(params[f"ctrlMel.{name}"]) for name, _ in MELLINGER_GAINS}
        rot = quat_to_rot(quat)
        est_yaw = math.atan2(rot[1, 0], rot[0, 0])
        e_p = np.asarray(sp.position, np.float64) - pos
        e_v = np.asarray(sp.velocity, np.float64) - vel
        lim = np.array([g["i_range_xy"], g["i_range_xy"], g["i_range_z"]])
        self.i_pos = np.clip(self.i_pos + e_p * dt, -lim, lim)
        if sp.mode_yaw == VELOCITY:
            yaw = est_yaw + sp.rates[2] * dt
        elif sp.mode_yaw == ABS:
            yaw = float(sp.attitude[2])
        else:
            yaw = 0.0
        kp = np.array([g["kp_xy"], g["kp_xy"], g["kp_z"]])
        kd = np.array([g["kd_xy"], g["kd_xy"], g["kd_z"]])
        ki = np.array([g["ki_xy"], g["ki_xy"], g["ki_z"]])
        feedback = kp * e_p + kd * e_v + ki * self.i_pos
        if sp.mode_x == ABS:
            force = g["mass"] * (np.asarray(sp.acceleration, np.float64) + [0.0, 0.0, GRAVITY]) + feedback
            desired = _axes_from(_unit(force), yaw)
        elif sp.mode_roll == ABS and sp.mode_pitch == ABS and sp.mode_z == DISABLE:
            force = None
            desired = rpy_to_rot(float(sp.attitude[0]), float(sp.attitude[1]), yaw)
        else:                                   # hold z, level, heading as estimated
            force = np.array([0.0, 0.0, g["mass"] * GRAVITY + feedback[2]])
            desired = _axes_from(_unit(force), est_yaw)
        skew = desired.T @ rot - rot.T @ desired
        e_r = np.array([skew[2, 1], skew[0, 2], skew[1, 0]])
        lim_m = np.array([g["i_range_m_xy"], g["i_range_m_xy"], g["i_range_m_z"]])
        self.i_att = np.clip(self.i_att - e_r * dt, -lim_m, lim_m)
        k_r = np.array([g["kR_xy"], g["kR_xy"], g["kR_z"]])
        k_w = np.array([g["kw_xy"], g["kw_xy"], g["kw_z"]])
        k_im = np.array([g["ki_m_xy"], g["ki_m_xy"], g["ki_m_z"]])
        rates = np.asarray(sp.rates, np.float64) + (-k_r * e_r + k_im * self.i_att) / k_w
        rates = np.clip(rates, -RATE_LIMIT, RATE_LIMIT)
        if sp.mode_z == DISABLE or force is None:
            thrust = float(sp.thrust)
        else:
            thrust = min(MAX_COUNTS, max(0.0, g["massThrust"] * float(force @ rot[:, 2])))
        if thrust <= 0.0:
            self.reset()
            return 0.0, np.zeros(3)
        r_des = np.degrees([math.atan2(desired[2, 1], desired[2, 2]), -math.asin(max(-1.0, min(1.0, desired[2, 0]))),
                            math.atan2(desired[1, 0], desired[0, 0])])
        self.debug = {"cmd_thrust": thrust, "roll": r_des[0], "pitch": r_des[1], "yaw": r_des[2],
                      "rollRate": math.degrees(rates[0]), "pitchRate": math.degrees(rates[1]),
                      "yawRate": math.degrees(rates[2])}
        return thrust, rates
