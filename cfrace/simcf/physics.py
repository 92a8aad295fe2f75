"""The physics behind SimFleet: the training simulator itself (cfrace.sim.simulator.Simulator), one world.

There is no second copy of the model: the simulated Crazyflies step the C kernel (real time: about
40 us per 2 ms step for two drones, one thread; benchmarks/simcf_step.py) or, without a C
compiler, the torch path (the same model, far slower than real time for one world).
"""

from __future__ import annotations

import torch

from cfrace.drone import DroneProfile
from cfrace.errors import ConfigError
from cfrace.sim import ckernel
from cfrace.sim.dynamics import hover_motor_speed
from cfrace.sim.simulator import REASONS, CrashRules, Simulator
from cfrace.track import Track

BACKENDS = ("auto", "c", "torch")


def make_physics(track: Track, profile: DroneProfile, drones: int, *, backend: str = "auto", obstacles: bool = True,
                 crash_rules=None, seed: int = 0) -> tuple["OneWorld", str]:
    """-> (simulator, backend name). backend: auto (the C kernel if it builds, else torch), c or torch."""
    if backend not in BACKENDS:
        raise ConfigError(f"simcf: unknown backend {backend!r} ({', '.join(BACKENDS)})")
    # A real drone may sit on the floor and leave the arena: only impacts, gate frames and
    # long contacts end in a crash (the simulator then freezes the drone, motors off).
    rules = crash_rules or CrashRules(floor_grace_s=None, arena=False)
    if backend == "auto":
        backend = "c" if ckernel.available() else "torch"
    return OneWorld(track, profile, drones, obstacles=obstacles, rules=rules, seed=seed, backend=backend), backend


def crash_reason(code: int) -> str:
    return REASONS.get(code, str(code)) if code else ""


class OneWorld:
    """One world of the training simulator with numpy in and out: ``reset(pos, vel, quat, target)``,
    ``step(thrust (D,) N, rates (D, 3) rad/s, substeps)`` and numpy arrays pos, vel (D, 3), quat
    (D, 4) wxyz, omega (D, 3), crashed (D,) bool, reason (D,) int."""

    def __init__(self, track: Track, profile: DroneProfile, drones: int, *, obstacles: bool, rules, seed: int = 0,
                 backend: str = "c"):
        self.sim = Simulator(track, profile, worlds=1, drones=drones, obstacles=obstacles, seed=seed, rules=rules,
                             backend=backend, threads=1)

    def reset(self, pos, vel, quat, target) -> None:
        f32 = torch.float32
        self.sim.reset(torch.zeros(1, dtype=torch.int64), torch.tensor(pos, dtype=f32)[None],
                       torch.tensor(vel, dtype=f32)[None], torch.tensor(quat, dtype=f32)[None],
                       torch.tensor(target, dtype=torch.int64)[None])

    def set_drone(self, i: int, pos, vel, quat) -> None:
        """Put drone i at pos (3,) with velocity vel (3,) and attitude quat (4,) wxyz, body rates 0,
        rotors at hover speed if airborne (scenarios and tests: a drone already in flight)."""
        s, f32 = self.sim.state, torch.float32
        s.pos[0, i] = torch.tensor(pos, dtype=f32)
        s.vel[0, i] = torch.tensor(vel, dtype=f32)
        q = torch.tensor(quat, dtype=f32)
        s.quat[0, i] = q / q.norm()
        s.omega[0, i], s.pid_int[0, i], s.omega_prev[0, i] = 0.0, 0.0, 0.0
        s.motor[0, i] = float(hover_motor_speed(self.sim.profile)) if float(pos[2]) > self.sim.z_rest + 1e-3 else 0.0

    def step(self, thrust, rates, substeps: int) -> None:
        self.sim.step(torch.tensor(thrust, dtype=torch.float32)[None], torch.tensor(rates, dtype=torch.float32)[None],
                      substeps=substeps)
        # the training simulator freezes a crashed drone where it crashed; a real one falls: put it on the
        # floor, so that mocap (and the flight stack's floor check) sees a drone that is down
        down = self.sim.race.crashed[0]
        if bool(down.any()):
            self.sim.state.pos[0, down, 2] = self.sim.z_rest


def _world_view(part: str, name: str) -> property:
    return property(lambda self: getattr(getattr(self.sim, part), name)[0].detach().cpu().numpy(),
                    doc=f"numpy view of the simulator's {part}.{name} of the one world")


for _part, _names in (("state", ("pos", "vel", "quat", "omega", "motor")), ("race", ("crashed", "reason"))):
    for _name in _names:
        setattr(OneWorld, _name, _world_view(_part, _name))
