"""The physics behind SimFleet: the training simulator (C kernel or torch) or the real-time twin.

All expose the NumpySim interface: ``reset(pos, vel, quat, target)``, ``step(thrust (D,),
rates (D, 3), substeps)`` and numpy arrays ``pos, vel, quat, omega, crashed, reason``.
"""

from __future__ import annotations

from cfrace.drone import DroneProfile
from cfrace.errors import ConfigError
from cfrace.track import Track


def make_physics(track: Track, profile: DroneProfile, drones: int, *, backend: str = "auto", obstacles: bool = True,
                 crash_rules=None, seed: int = 0):
    """-> (simulator, backend name). backend: auto (C kernel if it builds, else numpy), c, torch, numpy."""
    from cfrace.sim.simulator import CrashRules

    # A real drone may sit on the floor and leave the arena: only impacts, gate frames and
    # long contacts end in a crash (the simulator then freezes the drone, motors off).
    rules = crash_rules or CrashRules(floor_grace_s=None, arena=False)
    if backend == "auto":
        from cfrace.sim import ckernel

        backend = "c" if ckernel.available() else "numpy"
    if backend == "numpy":
        from cfrace.simcf.npsim import NumpySim

        return NumpySim(track, profile, drones, obstacles=obstacles, rules=rules), backend
    if backend in ("c", "torch"):
        return TorchSimAdapter(track, profile, drones, obstacles=obstacles, rules=rules, seed=seed,
                               backend=backend), backend
    raise ConfigError(f"simcf: unknown backend {backend!r} (auto, c, torch or numpy)")


def crash_reason(code: int) -> str:
    from cfrace.sim.simulator import REASONS

    return REASONS.get(code, str(code)) if code else ""


class TorchSimAdapter:
    """cfrace.sim.simulator.Simulator (one world) behind the NumpySim interface: numpy in and out.
    The training simulator itself; real-time capable with its C kernel (backend "c", one thread),
    not with its torch path (several ms per 2 ms step for one world; see npsim.py)."""

    def __init__(self, track: Track, profile: DroneProfile, drones: int, *, obstacles: bool, rules, seed: int = 0,
                 backend: str = "c"):
        from cfrace.sim.simulator import Simulator

        self.sim = Simulator(track, profile, worlds=1, drones=drones, obstacles=obstacles, seed=seed, rules=rules,
                             backend=backend, threads=1)

    def reset(self, pos, vel, quat, target) -> None:
        import torch

        f32 = torch.float32
        self.sim.reset(torch.zeros(1, dtype=torch.int64), torch.tensor(pos, dtype=f32)[None],
                       torch.tensor(vel, dtype=f32)[None], torch.tensor(quat, dtype=f32)[None],
                       torch.tensor(target, dtype=torch.int64)[None])

    def step(self, thrust, rates, substeps: int) -> None:
        import torch

        self.sim.step(torch.tensor(thrust, dtype=torch.float32)[None], torch.tensor(rates, dtype=torch.float32)[None],
                      substeps=substeps)
        # the training simulator freezes a crashed drone where it crashed; a real one falls: put it on the
        # floor, so that mocap (and the flight stack's floor check) sees a drone that is down
        down = self.sim.race.crashed[0]
        if bool(down.any()):
            self.sim.state.pos[0, down, 2] = self.sim.z_rest

    def __getattr__(self, name):
        if name in ("pos", "vel", "quat", "omega", "crashed", "reason"):
            return getattr(self.sim, name)[0].detach().cpu().numpy()
        raise AttributeError(name)
