"""The batched racing simulator: dynamics + floor, arena, gates, obstacles, drones, race progress.

State is float32 tensors shaped (W worlds, D drones, ...) on one device. ``step`` holds one
command (collective thrust N, body rates rad/s) for ``substeps`` physics steps of 2 ms (10 = one
50 Hz policy step). Crashed drones are frozen until their world is reset.
Crash rules (the authors' training code, Jirl-upenn/AgileFlight_MultiAgent
ma_quadcopter_env.py): gate-frame hit, leaving the arena, z above the ceiling, z below 0.1 m after
the first 1.0 s, hitting the floor fast, contact longer than ``long_contact_s``.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import NamedTuple

import torch

from cfrace.drone import DroneProfile
from cfrace.errors import CfraceWarning
from cfrace.sim import ckernel
from cfrace.sim import collisions as col
from cfrace.sim.dynamics import PHYSICS_DT, Constants, DroneParams, DroneState, hover_motor_speed, physics_step, quat_to_rot
from cfrace.sim.gates import crossing, to_gate_frame
from cfrace.track import Track

# crash reasons (StepEvents.reason)
NONE, FLOOR, CEILING, ARENA, GATE_FRAME, LONG_CONTACT = 0, 1, 2, 3, 4, 5
REASONS = {NONE: "none", FLOOR: "floor", CEILING: "ceiling", ARENA: "arena", GATE_FRAME: "gate_frame",
           LONG_CONTACT: "long_contact"}


@dataclass(frozen=True)
class CrashRules:
    floor_grace_s: float | None = 1.0   #: s; after this, z < floor_z is a crash (None: never)
    floor_z: float = 0.1                #: m
    floor_impact_speed: float = 2.0     #: m/s; touching the floor faster than this is a crash
    long_contact_s: float = 0.3         #: s of continuous contact that ends in a crash
    arena: bool = True                  #: leaving the arena or the ceiling is a crash


class RaceState(NamedTuple):
    target: torch.Tensor        # (W, D) int64 next gate index
    gates_passed: torch.Tensor  # (W, D) int64
    laps: torch.Tensor          # (W, D) int64
    lap_start: torch.Tensor     # (W, D) s, world time the current lap started
    lap_last: torch.Tensor      # (W, D) s, duration of the last completed lap (nan before)
    crashed: torch.Tensor       # (W, D) bool, sticky
    reason: torch.Tensor        # (W, D) int64 crash reason
    contact_time: torch.Tensor  # (W, D) s of continuous contact
    time: torch.Tensor          # (W,) s since reset


class StepEvents(NamedTuple):
    gates: torch.Tensor        # (W, D) int64 gates passed during the step
    laps: torch.Tensor         # (W, D) int64 laps completed during the step
    crashed_now: torch.Tensor  # (W, D) bool
    contact: torch.Tensor      # (W, D) bool, any contact during the step
    reason: torch.Tensor       # (W, D) int64 crash reason (0 if none)

    def then(self, later: "StepEvents") -> "StepEvents":
        """The events of one policy step flown as two simulator calls, this one first (the flight
        observations' mid-step pose sample): counts add, flags or, the first crash's reason stays."""
        return StepEvents(self.gates + later.gates, self.laps + later.laps, self.crashed_now | later.crashed_now,
                          self.contact | later.contact, torch.where(self.crashed_now, self.reason, later.reason))


class Geometry(NamedTuple):
    gates: torch.Tensor        # (G, 4) [x, y, z, yaw]
    bars: col.Boxes            # gate frame bars
    obstacles: col.Boxes


def _substep(s: DroneState, r: RaceState, thrust, rates, p: DroneParams, g: Geometry, c: Constants,
             rules: CrashRules, radius: float, z_rest: float, arena: tuple, outer_half: float):
    """One 2 ms step of everything. Returns new states and per-substep events."""
    new, _ = physics_step(s, thrust, rates, p, c)
    pos, vel = new.pos, new.vel
    t = r.time.unsqueeze(-1) + c.dt                                   # (W, 1)
    # floor: rest on it, crash on a fast impact or (after the grace time) any low flight
    below = pos[..., 2] < z_rest
    impact = below & (vel[..., 2] < -rules.floor_impact_speed)
    pos = torch.cat([pos[..., :2], torch.maximum(pos[..., 2:], torch.full_like(pos[..., 2:], z_rest))], -1)
    on_floor = below.unsqueeze(-1)
    vel = torch.where(on_floor, torch.zeros_like(vel), vel)
    omega = torch.where(on_floor, torch.zeros_like(new.omega), new.omega)
    w, x, y, z = new.quat.unbind(-1)
    yaw_q = torch.stack([w, torch.zeros_like(x), torch.zeros_like(y), z], -1)
    yaw_q = yaw_q * torch.rsqrt((yaw_q * yaw_q).sum(-1, keepdim=True).clamp_min(1e-12))
    quat = torch.where(on_floor, yaw_q, new.quat)
    crash = impact
    reason = torch.where(impact, FLOOR, NONE)
    if rules.floor_grace_s is not None:
        low = (pos[..., 2] < rules.floor_z) & (t > rules.floor_grace_s)
        reason = torch.where(low & ~crash, FLOOR, reason)
        crash = crash | low
    if rules.arena:
        out = ((pos[..., 0] < arena[0]) | (pos[..., 0] > arena[1]) | (pos[..., 1] < arena[2])
               | (pos[..., 1] > arena[3]))
        ceil = pos[..., 2] > arena[4]
        reason = torch.where(ceil & ~crash, CEILING, reason)
        crash = crash | ceil
        reason = torch.where(out & ~crash, ARENA, reason)
        crash = crash | out
    # gate frames: touching a bar, or crossing the target gate's plane off-centre
    gate = g.gates[r.target]                                          # (W, D, 4)
    prev_local = to_gate_frame(s.pos, gate)
    local = to_gate_frame(pos, gate)
    passed, plane_hit = crossing(prev_local, local, outer_half)
    bar_hit = col.any_box_hit(pos, g.bars, radius) | plane_hit
    reason = torch.where(bar_hit & ~crash, GATE_FRAME, reason)
    crash = crash | bar_hit
    # obstacles and other drones: contacts
    pos, vel, contact = col.push_out_of_boxes(pos, vel, g.obstacles, radius)
    pos, vel, dd = col.drone_contacts(pos, vel, ~r.crashed, radius)
    contact = (contact | dd) & ~r.crashed
    contact_time = torch.where(contact, r.contact_time + c.dt, torch.zeros_like(r.contact_time))
    long_c = contact_time > rules.long_contact_s
    reason = torch.where(long_c & ~crash, LONG_CONTACT, reason)
    crash = crash | long_c
    # race progress (a crash in the same step voids the pass)
    passed = passed & ~crash & ~r.crashed
    gates_passed = r.gates_passed + passed
    num_gates = g.gates.shape[0]
    target = torch.where(passed, (r.target + 1) % num_gates, r.target)
    lap = passed & (gates_passed % num_gates == 0)
    lap_last = torch.where(lap, t - r.lap_start, r.lap_last)
    lap_start = torch.where(lap, t.expand_as(r.lap_start), r.lap_start)
    # crashed drones (before or now) keep their old state, motors off
    frozen = r.crashed.unsqueeze(-1)
    out_state = DroneState(
        torch.where(frozen, s.pos, pos), torch.where(frozen, torch.zeros_like(vel), vel),
        torch.where(frozen, s.quat, quat), torch.where(frozen, torch.zeros_like(omega), omega),
        torch.where(frozen | crash.unsqueeze(-1), torch.zeros_like(new.motor), new.motor),
        torch.where(frozen, s.pid_int, new.pid_int), torch.where(frozen, s.omega_prev, new.omega_prev))
    crash_now = crash & ~r.crashed
    out_race = RaceState(
        torch.where(r.crashed, r.target, target), torch.where(r.crashed, r.gates_passed, gates_passed),
        torch.where(r.crashed, r.laps, r.laps + lap), lap_start, lap_last, r.crashed | crash,
        torch.where(crash_now, reason, r.reason), contact_time, r.time + c.dt)
    live = ~r.crashed
    return out_state, out_race, (passed & live).long(), (lap & live).long(), crash_now, contact & live


def _step(s, r, thrust, rates, p, g, c, rules, radius, z_rest, arena, outer_half, substeps: int):
    gates = torch.zeros_like(r.gates_passed)
    laps = torch.zeros_like(r.laps)
    crashed = torch.zeros_like(r.crashed)
    contact = torch.zeros_like(r.crashed)
    for _ in range(substeps):
        s, r, dg, dl, cn, ct = _substep(s, r, thrust, rates, p, g, c, rules, radius, z_rest, arena, outer_half)
        gates, laps, crashed, contact = gates + dg, laps + dl, crashed | cn, contact | ct
    return s, r, StepEvents(gates, laps, crashed, contact, torch.where(crashed, r.reason, 0))


def _auto_backend(device: torch.device, drones: int) -> str:
    """"c" when the C kernel can take this simulator, else "torch"; on a CPU the fallback is several
    times slower, so it says why (a CfraceWarning)."""
    fits = device.type == "cpu" and drones <= ckernel.MAX_DRONES and ckernel.available()
    if device.type == "cpu" and not fits:
        why = (f"{drones} drones per world (the C kernel takes at most {ckernel.MAX_DRONES})"
               if drones > ckernel.MAX_DRONES else f"no C kernel ({ckernel.build_error()})")
        warnings.warn(f"simulator: {why}; falling back to the slower torch path", CfraceWarning, stacklevel=3)
    return "c" if fits else "torch"


class Simulator:
    """Batched simulator of W worlds x D drones racing on one track."""

    dt = PHYSICS_DT

    def __init__(self, track: Track, profile: DroneProfile, worlds: int, drones: int, *, obstacles: bool = True,
                 device: str | torch.device = "cpu", seed: int = 0, compile: bool = False,
                 rules: CrashRules = CrashRules(), backend: str = "auto", threads: int | None = None):
        """backend: "c" (fused C kernel, CPU only, at most ckernel.MAX_DRONES drones per world), "torch"
        (reference; CPU or CUDA; ``compile`` applies) or "auto" (C when it can, else torch)."""
        self.track, self.profile = track, profile
        self.num_worlds, self.num_drones = worlds, drones
        self.device = torch.device(device)
        self.obstacles = obstacles
        self.obstacle_scale = 1.0   #: the obstacles' size (set_obstacle_scale); 1 = as the track defines them
        self.rules = rules
        self.consts = Constants.from_profile(profile, self.dt)
        self.radius = profile.collision_radius
        self.z_rest = profile.collision_box[2] / 2.0
        a = track.arena
        self.arena = (a.x[0], a.x[1], a.y[0], a.y[1], a.z_max)
        self.outer_half = track.gate.outer / 2.0
        self.generator = torch.Generator(device=self.device).manual_seed(seed)
        dev, f32 = self.device, torch.float32
        bars = track.gate_bars()
        obst = track.obstacle_boxes() if obstacles else track.without_obstacles().obstacle_boxes()
        self.geometry = Geometry(torch.as_tensor(track.gate_array(), dtype=f32, device=dev),
                                 col.make_boxes(*bars, device=dev), col.make_boxes(*obst, device=dev))
        self.gate_corners = torch.as_tensor(track.gate_corners(), dtype=f32, device=dev)   # (G, 4, 3)
        w, d = worlds, drones
        z3 = torch.zeros(w, d, 3, dtype=f32, device=dev)
        quat = torch.zeros(w, d, 4, dtype=f32, device=dev)
        quat[..., 0] = 1.0
        pos = z3.clone()
        pos[..., 2] = self.z_rest
        self.state = DroneState(pos, z3.clone(), quat, z3.clone(), torch.zeros(w, d, 4, dtype=f32, device=dev),
                                z3.clone(), z3.clone())
        zl = torch.zeros(w, d, dtype=torch.int64, device=dev)
        zf = torch.zeros(w, d, dtype=f32, device=dev)
        self.race = RaceState(zl.clone(), zl.clone(), zl.clone(), zf.clone(), torch.full_like(zf, float("nan")),
                              torch.zeros(w, d, dtype=torch.bool, device=dev), zl.clone(), zf.clone(),
                              torch.zeros(w, dtype=f32, device=dev))
        self.scales = {k: torch.ones(w, d, n, dtype=f32, device=dev)
                       for k, n in (("kp", 3), ("ki", 3), ("kd", 3), ("k_aero", 3), ("tau_m", 1))}
        self._update_params()
        if backend == "auto":
            backend = _auto_backend(self.device, drones)
        if backend == "c" and (self.device.type != "cpu" or not ckernel.available()):
            raise RuntimeError(f"the C kernel needs a CPU device and a C compiler ({ckernel.build_error()})")
        if backend == "c" and drones > ckernel.MAX_DRONES:
            raise ValueError(f"the C kernel takes at most {ckernel.MAX_DRONES} drones per world, not {drones} "
                             f"(backend torch or auto)")
        if backend not in ("c", "torch"):
            raise ValueError(f"unknown simulator backend {backend!r}")
        self.backend = backend
        self.threads = threads or torch.get_num_threads()
        self._kernel = None
        if backend == "c":
            cst = ckernel.constants_array(self.consts, self.radius, self.z_rest, self.arena, self.outer_half, rules)
            self._kernel = ckernel.Kernel(cst, self.geometry, worlds, drones, self.threads)
        self._step_fn = _step
        if compile and backend == "torch":
            self._step_fn = torch.compile(_step, dynamic=False, fullgraph=False)

    # ----------------------------------------------------------------- parameters
    def set_obstacle_scale(self, scale: float) -> None:
        """Grow or shrink the obstacles (Track.obstacle_boxes(scale): the obstacle curriculum); the
        boxes are rewritten in place, so both backends see them at the next step."""
        if not self.obstacles:
            return
        new = col.make_boxes(*self.track.obstacle_boxes(scale), device=self.device)
        for dst, src in zip(self.geometry.obstacles, new):
            dst.copy_(src)
        self.obstacle_scale = float(scale)

    def _update_params(self) -> None:
        pr, dev = self.profile, self.device
        base = lambda v: torch.tensor(v, dtype=torch.float32, device=dev)
        rp, yw = pr.pid_roll_pitch, pr.pid_yaw
        sc = self.scales
        tau = pr.tau_m * sc["tau_m"]
        self.params = DroneParams(base([rp.kp, rp.kp, yw.kp]) * sc["kp"], base([rp.ki, rp.ki, yw.ki]) * sc["ki"],
                                  base([rp.kd, rp.kd, yw.kd]) * sc["kd"], base(pr.k_aero) * sc["k_aero"],
                                  1.0 - torch.exp(-self.dt / tau))

    def set_scales(self, world_ids: torch.Tensor, **scales: torch.Tensor) -> None:
        """Domain randomisation: multiply nominal parameters of the given worlds.
        Keys kp, ki, kd, k_aero: (n, D, 3); tau_m: (n, D, 1). Others keep their scales."""
        for key, value in scales.items():
            if key not in self.scales:
                raise KeyError(f"unknown parameter scale {key!r}")
            self.scales[key][world_ids] = value.to(self.scales[key].dtype)
        self._update_params()

    # ----------------------------------------------------------------- state access
    # sim.pos, vel, quat, omega, motor (the drone state's tensors) and sim.target, crashed, ...
    # (the race state's): properties added below the class
    def rot(self) -> torch.Tensor:
        """(W, D, 3, 3) world-from-body."""
        return quat_to_rot(self.state.quat)

    # ----------------------------------------------------------------- stepping
    def step(self, thrust: torch.Tensor, rates: torch.Tensor, substeps: int = 10) -> StepEvents:
        """Hold (thrust (W, D) N, rates (W, D, 3) rad/s) for ``substeps`` x 2 ms.
        A non-finite command is treated as motors off (thrust 0, rates 0) for that drone."""
        thrust = thrust.to(self.device, torch.float32)
        rates = rates.to(self.device, torch.float32)
        if self._kernel is not None:  # the kernel treats non-finite commands itself
            return StepEvents(*self._kernel(self.state, self.race, self.params, thrust, rates, substeps))
        bad = ~(torch.isfinite(thrust) & torch.isfinite(rates).all(-1))
        if bool(bad.any()):
            thrust = torch.where(bad, 0.0, thrust)
            rates = torch.where(bad.unsqueeze(-1), 0.0, rates)
        self.state, self.race, events = self._step_fn(
            self.state, self.race, thrust, rates, self.params, self.geometry, self.consts, self.rules, self.radius,
            self.z_rest, self.arena, self.outer_half, substeps)
        return events

    def reset(self, world_ids: torch.Tensor, pos: torch.Tensor, vel: torch.Tensor | None = None,
              quat: torch.Tensor | None = None, target: torch.Tensor | None = None) -> None:
        """Reset the given worlds (others untouched). pos (n, D, 3); vel, quat, target optional."""
        ids = torch.as_tensor(world_ids, dtype=torch.int64, device=self.device)
        n, d = ids.shape[0], self.num_drones
        f32, dev = torch.float32, self.device
        pos = pos.to(dev, f32)
        vel = torch.zeros(n, d, 3, dtype=f32, device=dev) if vel is None else vel.to(dev, f32)
        if quat is None:
            quat = torch.zeros(n, d, 4, dtype=f32, device=dev)
            quat[..., 0] = 1.0
        quat = quat.to(dev, f32)
        quat = quat / quat.norm(dim=-1, keepdim=True)
        airborne = pos[..., 2] > self.z_rest + 1e-3
        motor = torch.where(airborne, hover_motor_speed(self.profile), 0.0).unsqueeze(-1).expand(n, d, 4)
        s = self.state
        s.pos[ids], s.vel[ids], s.quat[ids] = pos, vel, quat
        s.omega[ids], s.pid_int[ids], s.omega_prev[ids] = 0.0, 0.0, 0.0
        s.motor[ids] = motor.to(f32)
        r = self.race
        r.target[ids] = 0 if target is None else target.to(dev, torch.int64)
        r.gates_passed[ids], r.laps[ids], r.reason[ids] = 0, 0, 0
        r.lap_start[ids], r.lap_last[ids], r.contact_time[ids] = 0.0, float("nan"), 0.0
        r.crashed[ids], r.time[ids] = False, 0.0

    def crash_reasons(self) -> list[list[str]]:
        return [[REASONS[int(v)] for v in row] for row in self.race.reason.cpu()]


def _field(part: str, name: str) -> property:
    return property(lambda self: getattr(getattr(self, part), name), doc=f"self.{part}.{name}")


for _name in ("pos", "vel", "quat", "omega", "motor"):
    setattr(Simulator, _name, _field("state", _name))
for _name in RaceState._fields:
    setattr(Simulator, _name, _field("race", _name))
