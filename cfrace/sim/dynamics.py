"""Crazyflie dynamics as pure functions over batched tensors shaped (W worlds, D drones, ...).

Paper Sec. III-C, one 2 ms physics step:
    body-rate PID:   tau_des = I (Kp e - Kd d(omega)/dt + Ki int e),  e = omega_des - omega
    mixer:           f_des = A^-1 [f_z, tau_des],  omega_mot_des = clamp(sqrt(f_des / k_eta))
    motors:          first order, omega_mot += (omega_des - omega_mot) (1 - exp(-dt / tau_m))
    wrench:          f_i = k_eta omega_i^2,  [f_z, tau] = A f
    drag:            f_drag = -(sum omega_i) K_aero v_body
    rigid body:      m dv/dt = R (f_drag + [0, 0, f_z]) + m g;  I domega/dt = tau - omega x I omega
                     dq/dt = q (x) [0, omega] / 2 (renormalised)
Deliberate difference: the motor lag uses the exact discretisation of the first-order model
instead of the paper's explicit Euler step, which oscillates once domain randomisation makes
tau_m < dt (tau_m x 0.2 = 1 ms < 2 ms). Both agree to first order for tau_m >> dt.
Elementwise arithmetic only (no matmul), so results do not depend on the batch size.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import NamedTuple

import torch

from cfrace.drone import GRAVITY, DroneProfile

PHYSICS_DT = 0.002  #: s, one physics step (500 Hz: the body-rate PID, the motors, the integration)


class DroneState(NamedTuple):
    pos: torch.Tensor        # (W, D, 3) m, world
    vel: torch.Tensor        # (W, D, 3) m/s, world
    quat: torch.Tensor       # (W, D, 4) wxyz, world-from-body, unit
    omega: torch.Tensor      # (W, D, 3) rad/s, body
    motor: torch.Tensor      # (W, D, 4) rad/s rotor speeds
    pid_int: torch.Tensor    # (W, D, 3) rad, integrated rate error
    omega_prev: torch.Tensor  # (W, D, 3) rad/s, measured rate of the previous step (D term)


class DroneParams(NamedTuple):
    """Per-world, per-drone parameters (domain randomisation scales already applied)."""

    kp: torch.Tensor         # (W, D, 3) 1/s
    ki: torch.Tensor         # (W, D, 3) 1/s^2
    kd: torch.Tensor         # (W, D, 3) -
    k_aero: torch.Tensor     # (W, D, 3) N s/m per rad/s
    motor_alpha: torch.Tensor  # (W, D, 1) 1 - exp(-dt / tau_m)


@dataclass(frozen=True)
class Constants:
    """Profile constants as Python floats (they become literals in compiled code)."""

    dt: float
    mass: float
    inertia: tuple[float, float, float]
    k_eta: float
    k_ratio: float                           # k_m / k_eta, m
    rotor_x: tuple[float, float, float, float]
    rotor_y: tuple[float, float, float, float]
    dirs: tuple[float, float, float, float]
    mix: tuple[tuple[float, ...], ...]       # (4, 4) inverse allocation, rotor i row
    w_min: float
    w_max: float
    i_limit: tuple[float, float, float]

    @staticmethod
    def from_profile(profile: DroneProfile, dt: float = PHYSICS_DT) -> "Constants":
        import numpy as np

        inv = np.linalg.inv(profile.allocation())
        xy = profile.rotor_xy
        rp, yw = profile.pid_roll_pitch, profile.pid_yaw
        return Constants(dt, profile.mass, tuple(profile.inertia), profile.k_eta, profile.k_m / profile.k_eta,
                         tuple(xy[:, 0]), tuple(xy[:, 1]), tuple(profile.rotor_dirs),
                         tuple(tuple(float(v) for v in row) for row in inv),
                         profile.motor_speed[0], profile.motor_speed[1], (rp.i_limit, rp.i_limit, yw.i_limit))


def quat_to_rot(q: torch.Tensor) -> torch.Tensor:
    """(..., 4) wxyz -> (..., 3, 3) rotation matrix."""
    w, x, y, z = q.unbind(-1)
    r = torch.stack([
        1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
        2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
        2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
    ], dim=-1)
    return r.unflatten(-1, (3, 3))


def _vec(values, ref: torch.Tensor) -> torch.Tensor:
    return torch.tensor(values, dtype=ref.dtype, device=ref.device)


def physics_step(s: DroneState, thrust: torch.Tensor, rates: torch.Tensor, p: DroneParams,
                 c: Constants) -> tuple[DroneState, torch.Tensor]:
    """One dt step. thrust (W, D) N desired collective, rates (W, D, 3) rad/s desired body rates.
    Returns the new state and the rotation matrix (W, D, 3, 3) of the new attitude."""
    dt = c.dt
    inertia = _vec(c.inertia, s.pos)
    # body-rate PID, derivative on the measured rate, torque = inertia x PID output
    err = rates - s.omega
    pid_int = torch.maximum(torch.minimum(s.pid_int + err * dt, _vec(c.i_limit, s.pos)), -_vec(c.i_limit, s.pos))
    d_meas = (s.omega - s.omega_prev) * (1.0 / dt)
    tau_des = inertia * (p.kp * err + p.ki * pid_int - p.kd * d_meas)
    # mixer: rotor forces from the inverse allocation, then rotor speeds (clamped)
    wrench = torch.cat([thrust.unsqueeze(-1), tau_des], dim=-1)            # (W, D, 4)
    m = c.mix
    f_des = torch.stack([wrench[..., 0] * m[i][0] + wrench[..., 1] * m[i][1] + wrench[..., 2] * m[i][2]
                         + wrench[..., 3] * m[i][3] for i in range(4)], dim=-1)
    w_des = torch.sqrt(f_des.clamp_min(0.0) * (1.0 / c.k_eta)).clamp(c.w_min, c.w_max)
    # first-order motors (exact discretisation)
    motor = s.motor + (w_des - s.motor) * p.motor_alpha
    f = c.k_eta * motor * motor                                            # (W, D, 4) N
    f_z = f.sum(-1)
    tau = torch.stack([
        f[..., 0] * c.rotor_y[0] + f[..., 1] * c.rotor_y[1] + f[..., 2] * c.rotor_y[2] + f[..., 3] * c.rotor_y[3],
        -(f[..., 0] * c.rotor_x[0] + f[..., 1] * c.rotor_x[1] + f[..., 2] * c.rotor_x[2] + f[..., 3] * c.rotor_x[3]),
        c.k_ratio * (f[..., 0] * c.dirs[0] + f[..., 1] * c.dirs[1] + f[..., 2] * c.dirs[2] + f[..., 3] * c.dirs[3]),
    ], dim=-1)
    rot = quat_to_rot(s.quat)                                              # (W, D, 3, 3)
    v_body = (rot * s.vel.unsqueeze(-1)).sum(-2)                           # R^T v
    force_b = -motor.sum(-1, keepdim=True) * p.k_aero * v_body             # drag, body frame
    force_b = force_b + torch.stack([torch.zeros_like(f_z), torch.zeros_like(f_z), f_z], dim=-1)
    acc = (rot * force_b.unsqueeze(-2)).sum(-1) * (1.0 / c.mass)          # R f / m
    acc = acc - _vec((0.0, 0.0, GRAVITY), s.pos)
    # Euler's equation: I domega = tau - omega x (I omega)
    iw = inertia * s.omega
    gyro = torch.linalg.cross(s.omega, iw, dim=-1)
    omega_dot = (tau - gyro) / inertia
    # semi-implicit Euler
    vel = s.vel + acc * dt
    pos = s.pos + vel * dt
    omega = s.omega + omega_dot * dt
    w, x, y, z = s.quat.unbind(-1)
    ox, oy, oz = omega.unbind(-1)
    dq = torch.stack([-x * ox - y * oy - z * oz, w * ox + y * oz - z * oy,
                      w * oy - x * oz + z * ox, w * oz + x * oy - y * ox], dim=-1)
    quat = s.quat + dq * (0.5 * dt)
    quat = quat * torch.rsqrt((quat * quat).sum(-1, keepdim=True))
    new = DroneState(pos, vel, quat, omega, motor, pid_int, s.omega)
    return new, quat_to_rot(quat)


def hover_motor_speed(profile: DroneProfile) -> float:
    """rad/s of each rotor at hover."""
    return (profile.weight / 4.0 / profile.k_eta) ** 0.5
