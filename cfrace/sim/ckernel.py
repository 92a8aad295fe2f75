"""Build and call the fused C kernel (kernel.c) for CPU simulation.

Built once per machine with the system C compiler (``cc``/``gcc``) into ``~/.cache/cfrace``
(or ``$CFRACE_CACHE``), keyed by a hash of the source. If no compiler is found, ``available()``
is False and the simulator uses its torch path. ctypes releases the GIL during the call.
"""

from __future__ import annotations

import ctypes
import hashlib
import os
import shutil
import subprocess
import tempfile
from pathlib import Path

import torch

_SRC = Path(__file__).with_name("kernel.c")
_lib = None
_error: str | None = None
MIN_DRONES_PER_THREAD = 512  #: below this many drones per thread, use fewer threads


def _cache_dir() -> Path:
    return Path(os.environ.get("CFRACE_CACHE", Path.home() / ".cache" / "cfrace"))


def _build() -> ctypes.CDLL:
    src = _SRC.read_bytes()
    cc = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if cc is None:
        raise RuntimeError("no C compiler (cc/gcc) found")
    # -ffast-math: about 1.7x on this kernel; inputs are sanitised by Simulator.step (no NaN/inf reaches it)
    flags = ["-O3", "-march=native", "-ffast-math", "-fPIC", "-shared", "-fopenmp", "-std=c99"]
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
    """Pack constants in the order of the C enum."""
    from cfrace.drone import GRAVITY

    vals = [c.dt, c.mass, *c.inertia, c.k_eta, c.k_ratio, *c.rotor_x, *c.rotor_y, *c.dirs]
    vals += [v for row in c.mix for v in row]
    vals += [c.w_min, c.w_max, *c.i_limit, GRAVITY, radius, z_rest, *arena, outer_half,
             -1.0 if rules.floor_grace_s is None else rules.floor_grace_s, rules.floor_z, rules.floor_impact_speed,
             rules.long_contact_s, 1.0 if rules.arena else 0.0]
    return torch.tensor(vals, dtype=torch.float32)


def _ptr(t: torch.Tensor) -> ctypes.c_void_p:
    assert t.is_contiguous() and t.device.type == "cpu", "kernel tensors must be contiguous CPU tensors"
    return ctypes.c_void_p(t.data_ptr())


def step(cst: torch.Tensor, s, r, p, g, thrust: torch.Tensor, rates: torch.Tensor, substeps: int, threads: int):
    """Advance in place. s: DroneState, r: RaceState, p: DroneParams, g: Geometry. Returns event tensors."""
    w, d = s.pos.shape[:2]
    dev = s.pos.device
    ev_gates = torch.empty(w, d, dtype=torch.int64, device=dev)
    ev_laps = torch.empty_like(ev_gates)
    ev_crashed = torch.empty(w, d, dtype=torch.bool, device=dev)
    ev_contact = torch.empty_like(ev_crashed)
    ev_reason = torch.empty_like(ev_gates)
    thrust = thrust.contiguous()
    rates = rates.contiguous()
    if w * d < MIN_DRONES_PER_THREAD * threads:  # waking OpenMP threads costs more than small batches gain
        threads = max(1, (w * d) // MIN_DRONES_PER_THREAD)
    args = [cst, *s, r.target, r.gates_passed, r.laps, r.lap_start, r.lap_last, r.crashed, r.reason,
            r.contact_time, r.time, *p, g.gates, *g.bars, *g.obstacles, thrust, rates,
            ev_gates, ev_laps, ev_crashed, ev_contact, ev_reason]
    rc = _lib.cfrace_step(ctypes.c_int(w), ctypes.c_int(d), ctypes.c_int(g.gates.shape[0]),
                          ctypes.c_int(g.bars.centre.shape[0]), ctypes.c_int(g.obstacles.centre.shape[0]),
                          ctypes.c_int(substeps), ctypes.c_int(threads), *[_ptr(a) for a in args])
    if rc != 0:
        raise ValueError(f"C kernel refused the call (code {rc}): at most 16 drones per world")
    return ev_gates, ev_laps, ev_crashed, ev_contact, ev_reason
