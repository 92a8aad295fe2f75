"""RaceEnv's part of the lab loop (cfrace.loopmodel): the 100 Hz pose history, the frames the
flight stack's estimator would read from it (delayed, noisy, dropped, predicted forward), late
setpoints and the drone-model draw. A mixin of cfrace.env.race_env.RaceEnv, which calls these
hooks where its reset and step need them; the rules themselves live in cfrace.loopmodel."""

from __future__ import annotations

import torch

from cfrace.loopmodel import (MOCAP_PERIOD_S, body_rates, frame_age, interpolate_pose, perturb_pose,
                              predict_commanded, rotate_body)

MOCAP_DT = MOCAP_PERIOD_S   #: s, one mocap frame (the env's mid-step pose sample)
HISTORY = 8   #: 100 Hz poses kept for the loop model's delayed frames (70 ms back)


class LabLoop:
    """Hooks of RaceEnv for its ``loop`` (LoopRanges) and ``drone`` (DroneRanges)."""

    def _init_lab(self, e: int, a: int, dev) -> None:
        """The per-world loop and drone state, saved with the env (``_extra``)."""
        loop, drone = self.loop, self.drone
        if loop is not None:
            z = lambda *shape: torch.zeros(e, a, *shape, device=dev)
            self.hist_pos, self.hist_quat = z(HISTORY, 3), z(HISTORY, 4)   #: newest first, 10 ms apart
            self.lp_latency, self.lp_noise, self.lp_att, self.lp_drop = z(), z(), z(), z()
            self.lp_late, self.lp_comp, self.lp_fresh = (torch.zeros(e, a, dtype=torch.bool, device=dev) for _ in range(3))
            self.prev_thrust, self.prev_rates = z(), z(3)
            self.cmd_acc = z()   #: m/s^2, the collective acceleration last commanded (the prediction's)
            self._extra += ("hist_pos", "hist_quat", "lp_latency", "lp_noise", "lp_att", "lp_drop", "lp_late",
                            "lp_comp", "lp_fresh", "prev_thrust", "prev_rates", "cmd_acc")
        if drone is not None:
            self.dr_gain, self.dr_cap, self.dr_floor = (torch.zeros(e, a, device=dev) for _ in range(3))
            self._extra += ("dr_gain", "dr_cap", "dr_floor")

    def _frame_at(self, age: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """(E, A) pose ages -> the poses then, between the 100 Hz samples of the history
        (interpolate_pose), with this frame's mocap noise (perturb_pose)."""
        k = (age / MOCAP_DT).clamp(0.0, HISTORY - 1.001)
        i0 = k.floor()
        w = (k - i0).unsqueeze(-1)
        i0 = i0.long().unsqueeze(-1).unsqueeze(-1)
        take = lambda h, i: torch.gather(h, 2, i.expand(*i.shape[:-1], h.shape[-1])).squeeze(2)
        hp, hq = self.hist_pos, self.hist_quat
        pos, quat = interpolate_pose(take(hp, i0), take(hq, i0), take(hp, i0 + 1), take(hq, i0 + 1), w)
        e, a = age.shape
        att = self._randn(e, a, 3) if self.loop.att_noise_rad[1] > 0 else None
        return perturb_pose(pos, quat, self._randn(e, a, 3), self.lp_noise.unsqueeze(-1), att,
                            self.lp_att.unsqueeze(-1))

    def _loop_observe(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """pos, vel, quat as the flight stack's estimator (cfrace.flight.mocap.estimation.PoseEstimator,
        velocity_alpha 1) reports them from the loop model's frames: the frame of this tick (age =
        latency + jitter) and the two before it, each noisy and maybe dropped; velocity the
        difference of the last two frames it got, position predicted forward by the age of its
        last frame plus the latency compensation (episodes with it; the pose age and a late
        setpoint's tick): after the episode's first command, as the commanded thrust flies it
        (predict_commanded; with compensation or without, the flight estimator's rule
        commanded_always), before it on the velocity; attitude turned forward at the body rates
        of the last two frames (with compensation)."""
        e, a = self.num_envs, self.num_agents
        age = frame_age(self.lp_latency, self.loop.jitter_s, self._rand(e, a))
        (p0, q0), (p1, q1), (p2, q2) = (self._frame_at(age + i * MOCAP_DT) for i in range(3))
        d0 = self._rand(e, a) < self.lp_drop                   # this tick's frame lost: hold the last one
        d1 = (self._rand(e, a) < self.lp_drop) & ~d0           # the one before lost: a 20 ms difference
        x0 = lambda m: m.unsqueeze(-1)
        base = torch.where(x0(d0), p1, p0)
        older = torch.where(x0(d0 | d1), p2, p1)
        span = torch.where(d1, 2 * MOCAP_DT, MOCAP_DT)
        vel = (base - older) / x0(span)
        q = torch.where(x0(d0), q1, q0)
        q_prev = torch.where(x0(d0 | d1), q2, q1)
        # compensation: the loop's delay as the lab measures it, the pose age and a late setpoint's tick
        comp = torch.where(self.lp_comp, self.lp_latency + MOCAP_DT * self.lp_late, torch.zeros_like(self.lp_latency))
        h = comp + torch.where(d0, MOCAP_DT, 0.0)
        pos = base + vel * x0(h)
        q_prev = q_prev * x0(1.0 - 2.0 * ((q * q_prev).sum(-1) < 0).float())
        turned = rotate_body(q, body_rates(q_prev, q, x0(span)), x0(h))
        quat = torch.where(x0(comp > 0), turned, q)
        cmd = x0(~self.lp_fresh)
        c_pos, c_vel = predict_commanded(base, vel, q, x0(self.cmd_acc), x0(h), x0(span) * 0.5)
        return torch.where(cmd, c_pos, pos), torch.where(cmd, c_vel, vel), quat

    def _push_pose(self) -> None:
        """This instant's poses into the 100 Hz history (newest first)."""
        s = self.sim
        self.hist_pos = torch.cat([s.pos.unsqueeze(2), self.hist_pos[:, :, :-1]], 2)
        self.hist_quat = torch.cat([s.quat.unsqueeze(2), self.hist_quat[:, :, :-1]], 2)

    def _reset_drone(self, ids: torch.Tensor, u) -> None:
        """Drones of worlds ``ids``: a profile of the ranges (or a mix of two), jittered."""
        n, a = ids.shape[0], self.num_agents
        d, w = self.drone, self.profile.weight
        table = torch.tensor(d.table(), dtype=torch.float32, device=self.device)
        k = table.shape[0]
        i, j = ((self._rand(n, a) * k).long().clamp_max(k - 1) for _ in range(2))
        mix = torch.where(self._rand(n, a) < d.blend, self._rand(n, a), torch.zeros(n, a, device=self.device))
        row = table[i] + (table[j] - table[i]) * mix.unsqueeze(-1)
        ur = lambda r, *shape: u(r[0], r[1], *shape)
        pid = row[..., 3:4]
        self.sim.set_scales(ids, k_aero=ur(d.k_aero, 3), kp=(pid * ur(d.kp, 1)).expand(n, a, 3),
                            ki=(pid * ur(d.ki, 1)).expand(n, a, 3), kd=(pid * ur(d.kd, 1)).expand(n, a, 3),
                            tau_m=row[..., 0:1] * ur(d.tau_jitter, 1))
        self.dr_gain[ids] = ur(d.thrust_gain)
        self.dr_cap[ids] = row[..., 1] * ur(d.cap_jitter) * w
        self.dr_floor[ids] = row[..., 2] * ur(d.floor_jitter) * w

    def _reset_loop(self, ids: torch.Tensor, u) -> None:
        """Loop draws of worlds ``ids`` for their new episode; the history filled with the start pose."""
        n, a = ids.shape[0], self.num_agents
        lp = self.loop
        self.hist_pos[ids] = self.sim.pos[ids].unsqueeze(2).expand(n, a, HISTORY, 3)
        self.hist_quat[ids] = self.sim.quat[ids].unsqueeze(2).expand(n, a, HISTORY, 4)
        self.lp_latency[ids] = u(*lp.latency_s)
        self.lp_noise[ids] = u(*lp.noise_m)
        self.lp_att[ids] = u(*lp.att_noise_rad)
        self.lp_drop[ids] = u(*lp.drop)
        self.lp_late[ids] = self._rand(n, a) < lp.late
        self.lp_comp[ids] = self._rand(n, a) < lp.comp
        self.lp_fresh[ids] = True

    def _delivered(self, thrust: torch.Tensor) -> torch.Tensor:
        """The thrust this drone delivers for the command: gain, idle floor, limit."""
        return torch.minimum(torch.maximum(thrust * self.dr_gain, self.dr_floor), self.dr_cap)

    def _late_first_half(self, thrust: torch.Tensor, rates: torch.Tensor, half: int, acc: torch.Tensor):
        """The first tick of a step, with the command before where the setpoint lands late; ``acc``
        the collective acceleration the command asks (thrust / mass, before the drone's gain)."""
        sim = self.sim
        self.cmd_acc = acc
        late = self.lp_late & ~self.lp_fresh
        e1 = sim.step(torch.where(late, self.prev_thrust, thrust),
                      torch.where(late.unsqueeze(-1), self.prev_rates, rates), half)
        self.prev_thrust, self.prev_rates, self.lp_fresh = thrust, rates, torch.zeros_like(self.lp_fresh)
        self._push_pose()
        return e1
