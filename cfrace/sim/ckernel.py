"""Build and call the fused C kernel (kernel.c) for CPU simulation.

Built once per machine with the system C compiler (``cc``/``gcc``) into ``~/.cache/cfrace``
(or ``$CFRACE_CACHE``), keyed by a hash of the source. If no compiler is found, ``available()``
is False and the simulator uses its torch path. ctypes releases the GIL during the call.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import platform
import shutil
import subprocess
import tempfile
from pathlib import Path

import torch

from cfrace.drone import GRAVITY
from cfrace.sim.gates import FRAME_HIT_HALF, PASS_HALF, PASS_RADIUS

_SRC = Path(__file__).with_name("kernel.c")
_lib = None
_error: str | None = None
MIN_DRONES_PER_THREAD = 512  #: below this many drones per thread, use fewer threads
MAX_DRONES = 16              #: drones per world the kernel takes (MAXD in kernel.c)


def _cache_dir() -> Path:
    return Path(os.environ.get("CFRACE_CACHE", Path.home() / ".cache" / "cfrace"))


def _build() -> ctypes.CDLL:
    src = _SRC.read_bytes()
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise RuntimeError("no C compiler (cc/gcc) found")
    # -ffast-math: about 1.7x on this kernel; inputs are sanitised by Simulator.step (no NaN/inf reaches it)
    flags = ["-O3", "-march=native", "-ffast-math", "-fPIC", "-shared", "-fopenmp", "-std=c99"]
    if platform.machine().lower() in ("x86_64", "amd64"):  # use 512-bit vectors where there are (1.4x here)
        flags.append("-mprefer-vector-width=512")
    flags += rule_defines()
    key = hashlib.sha256(src + " ".join([cc] + flags).encode()).hexdigest()[:16]
    out = _cache_dir() / f"cfrace_kernel_{key}.so"
    if not out.exists():
        out.parent.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=out.parent) as tmp:
            tmp_so = Path(tmp) / out.name
            proc = subprocess.run([cc, *flags, str(_SRC), "-o", str(tmp_so), "-lm"], capture_output=True, text=True)
            if proc.returncode != 0:
                raise RuntimeError(f"building {_SRC.name} failed: {proc.stderr.strip()[:500]}")
            os.replace(tmp_so, out)
    lib = ctypes.CDLL(str(out))
    lib.cfrace_step.restype = ctypes.c_int
    return lib


def rule_defines() -> list[str]:
    """The gate rule's constants (cfrace.sim.gates) as the C kernel's -D flags (float literals)."""
    return [f"-D{name}={float(v)!r}f" for name, v in
            (("PASS_RADIUS", PASS_RADIUS), ("PASS_HALF", PASS_HALF), ("FRAME_HIT_HALF", FRAME_HIT_HALF))]


def available() -> bool:
    """True when the kernel is (or can be) built on this machine."""
    global _lib, _error
    if os.environ.get("CFRACE_NO_CKERNEL"):
        return False
    if _lib is None and _error is None:
        try:
            _lib = _build()
        except (OSError, RuntimeError) as exc:
            _error = str(exc)
    return _lib is not None


def build_error() -> str | None:
    return _error


def constants_array(c, radius: float, z_rest: float, arena: tuple, outer_half: float, rules) -> torch.Tensor:
    """Pack constants in the order of the C enum (the gate rule's are build flags: rule_defines)."""
    vals = [c.dt, c.mass, *c.inertia, c.k_eta, c.k_ratio, *c.rotor_x, *c.rotor_y, *c.dirs]
    vals += [v for row in c.mix for v in row]
    vals += [c.w_min, c.w_max, *c.i_limit, GRAVITY, radius, z_rest, *arena, outer_half,
             -1.0 if rules.floor_grace_s is None else rules.floor_grace_s, rules.floor_z, rules.floor_impact_speed,
             rules.long_contact_s, 1.0 if rules.arena else 0.0]
    return torch.tensor(vals, dtype=torch.float32)


class Kernel:
    """The kernel bound to one simulator's tensors. The table of tensor addresses (the order of the
    P_ enum in kernel.c) is built once and rebuilt only when the state, race or parameter tuple is
    replaced (``Simulator.set_scales`` builds new parameter tensors); state is updated in place."""

    def __init__(self, cst: torch.Tensor, geometry, worlds: int, drones: int, threads: int):
        self.cst, self.geometry = cst, geometry
        self.w, self.d = worlds, drones
        if worlds * drones < MIN_DRONES_PER_THREAD * threads:  # waking OpenMP threads costs more than small batches gain
            threads = max(1, (worlds * drones) // MIN_DRONES_PER_THREAD)
        self.threads = threads
        self.sizes = (geometry.gates.shape[0], geometry.bars.centre.shape[0], geometry.obstacles.centre.shape[0])
        self._ptrs = (ctypes.c_void_p * _P_COUNT)()
        self._bound: tuple = ()

    def _bind(self, s, r, p) -> None:
        g = self.geometry
        tensors = [self.cst, *s, *r, *p, g.gates, *g.bars, *g.obstacles]
        assert len(tensors) == _P_THRUST, "the tensor list must follow the P_ enum in kernel.c"
        for i, t in enumerate(tensors):
            assert t.is_contiguous() and t.device.type == "cpu", "kernel tensors must be contiguous CPU tensors"
            self._ptrs[i] = t.data_ptr()
        self._bound = (s, r, p)

    def __call__(self, s, r, p, thrust: torch.Tensor, rates: torch.Tensor, substeps: int):
        """Advance in place. s: DroneState, r: RaceState, p: DroneParams; thrust (W, D), rates (W, D, 3)
        float32 (a non-finite command is motors off, in the kernel). Returns the event tensors."""
        b = self._bound
        if not b or b[0] is not s or b[1] is not r or b[2] is not p:
            self._bind(s, r, p)
        w, d = self.w, self.d
        thrust = thrust.contiguous()
        rates = rates.contiguous()
        if thrust.numel() != w * d or rates.numel() != 3 * w * d:
            raise ValueError(f"thrust/rates: expected ({w}, {d}) and ({w}, {d}, 3), got {tuple(thrust.shape)}, "
                             f"{tuple(rates.shape)}")
        ev_i = torch.empty(3, w, d, dtype=torch.int64)   # gates, laps, reason
        ev_b = torch.empty(2, w, d, dtype=torch.bool)    # crashed, contact
        ptrs, base_i, base_b = self._ptrs, ev_i.data_ptr(), ev_b.data_ptr()
        ptrs[_P_THRUST], ptrs[_P_RATES] = thrust.data_ptr(), rates.data_ptr()
        ptrs[_P_EV], ptrs[_P_EV + 1], ptrs[_P_EV + 4] = base_i, base_i + 8 * w * d, base_i + 16 * w * d
        ptrs[_P_EV + 2], ptrs[_P_EV + 3] = base_b, base_b + w * d
        rc = _lib.cfrace_step(w, d, *self.sizes, substeps, self.threads, ptrs)
        if rc != 0:
            raise ValueError(f"C kernel refused the call (code {rc}): at most 16 drones per world, 1-256 gates")
        gates, laps, reason = ev_i.unbind(0)
        crashed, contact = ev_b.unbind(0)
        return gates, laps, crashed, contact, reason


# slots of the address table (the P_ enum in kernel.c): 31 fixed tensors, then the command and the events
_P_THRUST, _P_RATES, _P_EV, _P_COUNT = 31, 32, 33, 38
