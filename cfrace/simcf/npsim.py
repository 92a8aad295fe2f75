"""A float64 twin of cfrace.sim.simulator.Simulator for ONE world, fast enough for real time.

Why: the torch simulator is built for thousands of worlds; for one world of two drones its
per-op overhead costs about 2-7 ms per 2 ms physics step on a laptop CPU, so it cannot keep up
with the wall clock. This module repeats the same model step for step (cfrace/sim/dynamics.py
physics_step, cfrace/sim/simulator.py _substep, cfrace/sim/collisions.py) in plain Python
floats per drone (tens of microseconds per step for a few drones, where numpy's per-call
overhead would dominate). tests/test_simcf_npsim.py checks it against the torch simulator,
trajectory by trajectory; change both together.
Public arrays (numpy, built on access): pos, vel (D, 3) world; quat (D, 4) wxyz world-from-body;
omega (D, 3) body rad/s; motor (D, 4) rad/s; crashed (D,) bool; reason, target, gates_passed,
laps (D,) int.
"""

from __future__ import annotations

import math

import numpy as np

from cfrace.drone import GRAVITY, DroneProfile
from cfrace.track import Track

PASS_HALF, PASS_RADIUS, FRAME_HIT_HALF = 0.5, 1.0, 0.4   # cfrace/sim/gates.py
FLOOR, CEILING, ARENA, GATE_FRAME, LONG_CONTACT = 1, 2, 3, 4, 5  # cfrace/sim/simulator.py reasons


class _Drone:
    """Mutable per-drone state, plain floats."""

    __slots__ = ("p", "v", "q", "w", "motor", "pid", "w_prev", "target", "gates_passed", "laps",
                 "crashed", "reason", "contact_time")

    def __init__(self, p, v, q, motor, target):
        self.p, self.v, self.q = list(p), list(v), list(q)
        self.w, self.pid, self.w_prev = [0.0] * 3, [0.0] * 3, [0.0] * 3
        self.motor = [motor] * 4
        self.target, self.gates_passed, self.laps = int(target), 0, 0
        self.crashed, self.reason, self.contact_time = False, 0, 0.0


def _boxes(centre, half, yaw) -> list[tuple]:
    """[(cx, cy, cz, hx, hy, hz, cos, sin, reach)], reach = xy radius of the box for a cheap cull."""
    out = []
    for c, h, y in zip(np.asarray(centre, float).reshape(-1, 3), np.asarray(half, float).reshape(-1, 3),
                       np.asarray(yaw, float).reshape(-1)):
        out.append((*map(float, c), *map(float, h), math.cos(y), math.sin(y), math.hypot(h[0], h[1])))
    return out


class NumpySim:
    """One world of D drones; the Simulator's dynamics, floor, gates, obstacles and crash rules."""

    dt = 0.002

    def __init__(self, track: Track, profile: DroneProfile, drones: int, *, obstacles: bool = True, rules=None):
        from cfrace.sim.simulator import CrashRules

        self.rules = rules or CrashRules()
        self.n = drones
        p = profile
        self.mass, self.k_eta, self.k_ratio = p.mass, p.k_eta, p.k_m / p.k_eta
        self.inertia = tuple(map(float, p.inertia))
        xy = p.rotor_xy
        self.rx, self.ry = tuple(map(float, xy[:, 0])), tuple(map(float, xy[:, 1]))
        self.dirs = tuple(map(float, p.rotor_dirs))
        self.mix = tuple(tuple(map(float, row)) for row in np.linalg.inv(p.allocation()))  # rotor i row
        self.w_min, self.w_max = map(float, p.motor_speed)
        rp, yw = p.pid_roll_pitch, p.pid_yaw
        self.kp, self.ki, self.kd = (rp.kp, rp.kp, yw.kp), (rp.ki, rp.ki, yw.ki), (rp.kd, rp.kd, yw.kd)
        self.i_limit = (rp.i_limit, rp.i_limit, yw.i_limit)
        self.k_aero = tuple(map(float, p.k_aero))
        self.alpha = 1.0 - math.exp(-self.dt / p.tau_m)
        self.radius = p.collision_radius
        self.z_rest = p.collision_box[2] / 2.0
        self.hover_speed = (p.weight / 4.0 / p.k_eta) ** 0.5
        a = track.arena
        self.arena = (a.x[0], a.x[1], a.y[0], a.y[1], a.z_max)
        self.outer_half = track.gate.outer / 2.0
        self.gates = [tuple(map(float, g)) for g in track.gate_array()]
        self.bars = _boxes(*track.gate_bars())
        self.obstacles = _boxes(*(track.obstacle_boxes() if obstacles else track.without_obstacles().obstacle_boxes()))
        pos = np.zeros((drones, 3))
        pos[:, 2] = self.z_rest
        self.reset(pos)

    # ----------------------------------------------------------------- state
    def reset(self, pos, vel=None, quat=None, target=None) -> None:
        d = self.n
        pos = np.asarray(pos, float).reshape(d, 3)
        vel = np.zeros((d, 3)) if vel is None else np.asarray(vel, float).reshape(d, 3)
        quat = np.tile([1.0, 0, 0, 0], (d, 1)) if quat is None else np.asarray(quat, float).reshape(d, 4)
        quat = quat / np.linalg.norm(quat, axis=-1, keepdims=True)
        target = np.zeros(d, np.int64) if target is None else np.asarray(target).reshape(d)
        self.drones = [_Drone(pos[i].tolist(), vel[i].tolist(), quat[i].tolist(),
                              self.hover_speed if pos[i, 2] > self.z_rest + 1e-3 else 0.0, target[i])
                       for i in range(d)]
        self.time = 0.0

    def _array(self, attr: str, dtype=float) -> np.ndarray:
        return np.array([getattr(s, attr) for s in self.drones], dtype=dtype)

    pos = property(lambda self: self._array("p"))
    vel = property(lambda self: self._array("v"))
    quat = property(lambda self: self._array("q"))
    omega = property(lambda self: self._array("w"))
    motor = property(lambda self: self._array("motor"))
    crashed = property(lambda self: self._array("crashed", bool))
    reason = property(lambda self: self._array("reason", np.int64))
    target = property(lambda self: self._array("target", np.int64))
    gates_passed = property(lambda self: self._array("gates_passed", np.int64))
    laps = property(lambda self: self._array("laps", np.int64))

    # ----------------------------------------------------------------- stepping
    def step(self, thrust, rates, substeps: int = 10) -> None:
        """Hold thrust (D,) N and body rates (D, 3) rad/s for substeps x 2 ms."""
        thrust = [float(v) for v in np.asarray(thrust, float).reshape(self.n)]
        rates = np.asarray(rates, float).reshape(self.n, 3).tolist()
        for _ in range(substeps):
            self._substep(thrust, rates)

    def _physics(self, s: _Drone, thrust: float, rates) -> tuple:
        """physics_step for one drone -> (p, v, q, w, motor, pid) new lists."""
        dt, inertia = self.dt, self.inertia
        w = s.w
        tau_des = [0.0] * 3
        pid = [0.0] * 3
        for k in range(3):
            err = rates[k] - w[k]
            lim = self.i_limit[k]
            pid[k] = max(-lim, min(lim, s.pid[k] + err * dt))
            d_meas = (w[k] - s.w_prev[k]) / dt
            tau_des[k] = inertia[k] * (self.kp[k] * err + self.ki[k] * pid[k] - self.kd[k] * d_meas)
        wrench = (thrust, tau_des[0], tau_des[1], tau_des[2])
        motor = [0.0] * 4
        f = [0.0] * 4
        for i in range(4):
            m = self.mix[i]
            fd = m[0] * wrench[0] + m[1] * wrench[1] + m[2] * wrench[2] + m[3] * wrench[3]
            wd = min(self.w_max, max(self.w_min, math.sqrt(max(fd, 0.0) / self.k_eta)))
            motor[i] = s.motor[i] + (wd - s.motor[i]) * self.alpha
            f[i] = self.k_eta * motor[i] * motor[i]
        f_z = f[0] + f[1] + f[2] + f[3]
        rx, ry, dirs = self.rx, self.ry, self.dirs
        tau = (f[0] * ry[0] + f[1] * ry[1] + f[2] * ry[2] + f[3] * ry[3],
               -(f[0] * rx[0] + f[1] * rx[1] + f[2] * rx[2] + f[3] * rx[3]),
               self.k_ratio * (f[0] * dirs[0] + f[1] * dirs[1] + f[2] * dirs[2] + f[3] * dirs[3]))
        qw, qx, qy, qz = s.q
        r = ((1 - 2 * (qy * qy + qz * qz), 2 * (qx * qy - qw * qz), 2 * (qx * qz + qw * qy)),
             (2 * (qx * qy + qw * qz), 1 - 2 * (qx * qx + qz * qz), 2 * (qy * qz - qw * qx)),
             (2 * (qx * qz - qw * qy), 2 * (qy * qz + qw * qx), 1 - 2 * (qx * qx + qy * qy)))
        v = s.v
        msum = motor[0] + motor[1] + motor[2] + motor[3]
        fb = [-msum * self.k_aero[j] * (r[0][j] * v[0] + r[1][j] * v[1] + r[2][j] * v[2]) for j in range(3)]
        fb[2] += f_z
        acc = [(r[i][0] * fb[0] + r[i][1] * fb[1] + r[i][2] * fb[2]) / self.mass for i in range(3)]
        acc[2] -= GRAVITY
        iw = (inertia[0] * w[0], inertia[1] * w[1], inertia[2] * w[2])
        gyro = (w[1] * iw[2] - w[2] * iw[1], w[2] * iw[0] - w[0] * iw[2], w[0] * iw[1] - w[1] * iw[0])
        v_new = [v[k] + acc[k] * dt for k in range(3)]
        p_new = [s.p[k] + v_new[k] * dt for k in range(3)]
        w_new = [w[k] + (tau[k] - gyro[k]) / inertia[k] * dt for k in range(3)]
        ox, oy, oz = w_new                                   # semi-implicit: the new rate turns q
        h = 0.5 * dt
        q = [qw + (-qx * ox - qy * oy - qz * oz) * h, qx + (qw * ox + qy * oz - qz * oy) * h,
             qy + (qw * oy - qx * oz + qz * ox) * h, qz + (qw * oz + qx * oy - qy * ox) * h]
        norm = math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        return p_new, v_new, [c / norm for c in q], w_new, motor, pid

    def _substep(self, thrust, rates) -> None:
        rules, dt = self.rules, self.dt
        t = self.time + dt
        new = []
        for i, s in enumerate(self.drones):
            if s.crashed:
                new.append(None)
                continue
            p, v, q, w, motor, pid = self._physics(s, thrust[i], rates[i])
            crash, reason = False, 0
            if p[2] < self.z_rest:                           # floor: rest on it, crash on a fast impact
                if v[2] < -rules.floor_impact_speed:
                    crash, reason = True, FLOOR
                p[2] = self.z_rest
                v, w = [0.0] * 3, [0.0] * 3
                yn = max(math.hypot(q[0], q[3]), 1e-6)
                q = [q[0] / yn, 0.0, 0.0, q[3] / yn]
            if rules.floor_grace_s is not None and p[2] < rules.floor_z and t > rules.floor_grace_s and not crash:
                crash, reason = True, FLOOR
            if rules.arena:
                a = self.arena
                if p[2] > a[4] and not crash:
                    crash, reason = True, CEILING
                if (p[0] < a[0] or p[0] > a[1] or p[1] < a[2] or p[1] > a[3]) and not crash:
                    crash, reason = True, ARENA
            passed, plane_hit = self._crossing(s.p, p, self.gates[s.target])
            if (plane_hit or self._touches(p, self.bars)) and not crash:
                crash, reason = True, GATE_FRAME
            contact = self._push_out(p, v)
            new.append([p, v, q, w, motor, pid, crash, reason, contact, passed])
        self._drone_contacts(new)
        for s, nw in zip(self.drones, new):
            if nw is None:                                   # frozen since an earlier crash
                s.v, s.w = [0.0] * 3, [0.0] * 3
                s.motor = [0.0] * 4
                continue
            p, v, q, w, motor, pid, crash, reason, contact, passed = nw
            s.contact_time = s.contact_time + dt if contact else 0.0
            if s.contact_time > rules.long_contact_s and not crash:
                crash, reason = True, LONG_CONTACT
            if passed and not crash:
                s.gates_passed += 1
                s.target = (s.target + 1) % len(self.gates)
                if s.gates_passed % len(self.gates) == 0:
                    s.laps += 1
            s.w_prev = s.w
            s.p, s.v, s.q, s.w, s.pid = p, v, q, w, pid
            s.motor = [0.0] * 4 if crash else motor
            if crash:
                s.crashed, s.reason = True, reason
        self.time = t

    # ----------------------------------------------------------------- geometry
    def _crossing(self, prev, cur, gate) -> tuple[bool, bool]:
        gx, gy, gz, yaw = gate
        c, s = math.cos(yaw), math.sin(yaw)
        px = c * (prev[0] - gx) + s * (prev[1] - gy)
        x = c * (cur[0] - gx) + s * (cur[1] - gy)
        if not (px > 0.0 and x <= 0.0):
            return False, False
        py, pz = -s * (prev[0] - gx) + c * (prev[1] - gy), prev[2] - gz
        y, z = -s * (cur[0] - gx) + c * (cur[1] - gy), cur[2] - gz
        frac = px / max(px - x, 1e-9)
        ay, az = abs(py + frac * (y - py)), abs(pz + frac * (z - pz))
        passed = math.sqrt(x * x + y * y + z * z) < PASS_RADIUS and ay < PASS_HALF and az < PASS_HALF
        inside = ay < self.outer_half and az < self.outer_half
        return passed, inside and (ay >= FRAME_HIT_HALF or az >= FRAME_HIT_HALF)

    def _touches(self, p, boxes) -> bool:
        rad = self.radius
        for cx, cy, cz, hx, hy, hz, c, s, reach in boxes:
            dx, dy = p[0] - cx, p[1] - cy
            if dx * dx + dy * dy > (reach + rad) ** 2:
                continue
            ex = max(abs(c * dx + s * dy) - hx, 0.0)
            ey = max(abs(-s * dx + c * dy) - hy, 0.0)
            ez = max(abs(p[2] - cz) - hz, 0.0)
            if math.sqrt(ex * ex + ey * ey + ez * ez) < rad:
                return True
        return False

    def _push_out(self, p, v) -> bool:
        """Resolve sphere-box contacts box by box, in place. Returns contact."""
        rad, contact = self.radius, False
        for cx, cy, cz, hx, hy, hz, c, s, reach in self.obstacles:
            dx, dy, dz = p[0] - cx, p[1] - cy, p[2] - cz
            if dx * dx + dy * dy > (reach + rad) ** 2:
                continue
            local = [c * dx + s * dy, -s * dx + c * dy, dz]
            half = (hx, hy, hz)
            clamped = [max(-half[k], min(half[k], local[k])) for k in range(3)]
            diff = [local[k] - clamped[k] for k in range(3)]
            dist = math.sqrt(diff[0] ** 2 + diff[1] ** 2 + diff[2] ** 2)
            if not dist < rad:
                continue
            if dist > 1e-9:
                n = [d / dist for d in diff]
            else:                                           # inside: leave along least penetration
                pen = [half[k] - abs(local[k]) for k in range(3)]
                k = pen.index(min(pen))
                n = [0.0, 0.0, 0.0]
                n[k] = 1.0 if local[k] >= 0 else -1.0
            local = [clamped[k] + n[k] * rad for k in range(3)]
            p[0], p[1], p[2] = c * local[0] - s * local[1] + cx, s * local[0] + c * local[1] + cy, local[2] + cz
            nw = (c * n[0] - s * n[1], s * n[0] + c * n[1], n[2])
            vn = v[0] * nw[0] + v[1] * nw[1] + v[2] * nw[2]
            if vn < 0:
                for k in range(3):
                    v[k] -= vn * nw[k]
            contact = True
        return contact

    def _drone_contacts(self, new) -> None:
        """Pairwise contacts among drones that were live before this step, in place."""
        live = [i for i, nw in enumerate(new) if nw is not None]
        rad2 = 2.0 * self.radius
        dp = {i: [0.0] * 3 for i in live}
        dv = {i: [0.0] * 3 for i in live}
        for i in live:
            for j in live:
                if i == j:
                    continue
                pi, pj = new[i][0], new[j][0]
                diff = [pi[k] - pj[k] for k in range(3)]
                dist = math.sqrt(diff[0] ** 2 + diff[1] ** 2 + diff[2] ** 2)
                if not dist < rad2:
                    continue
                n = [d / max(dist, 1e-6) for d in diff]
                depth = max(rad2 - dist, 0.0)
                vi, vj = new[i][1], new[j][1]
                rel = sum((vi[k] - vj[k]) * n[k] for k in range(3))
                for k in range(3):
                    dp[i][k] += 0.5 * depth * n[k]
                    if rel < 0:
                        dv[i][k] -= 0.5 * rel * n[k]
                new[i][8] = True
        for i in live:
            for k in range(3):
                new[i][0][k] += dp[i][k]
                new[i][1][k] += dv[i][k]
