"""The simulator benchmark behind `cfrace bench sim`: drone-steps per second of the batched simulator
(one drone advanced by one 2 ms physics step with the full model: motors, rate PID, drag, floor,
arena, gate frames and gate passing, obstacles, drone-drone contacts) with each backend (fused C
kernel, torch eager, torch.compile), and the crazyflow simulator (JAX, benchmarks/crazyflow_peer.py,
run with the python of its own venv) on the same numbers of drones.
"""

from __future__ import annotations

import hashlib
import json
import math
import os
import platform
import subprocess
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Callable, Optional

import torch

from cfrace.drone import load_profile
from cfrace.errors import CfraceError, ConfigError
from cfrace.paths import ROOT
from cfrace.sim import ckernel
from cfrace.sim.simulator import Simulator
from cfrace.track import load_track


def hover_start(track, worlds: int, drones: int):
    """(W, D, 3) start positions: 1.5 m before gate 0 on its approach side, drones 0.5 m apart."""
    x, y, z, yaw = track.gates[0]
    n = torch.tensor([math.cos(yaw), math.sin(yaw), 0.0])
    side = torch.tensor([-math.sin(yaw), math.cos(yaw), 0.0])
    offsets = (torch.arange(drones, dtype=torch.float32) - (drones - 1) / 2.0) * 0.5
    pos = torch.tensor([x, y, max(z, 1.0)]) + 1.5 * n + offsets[:, None] * side   # (D, 3)
    return pos.expand(worlds, drones, 3).clone()


def gates_start(track, worlds: int, drones: int):
    """(W, D, 3) start positions 0.6 m before gate (w mod G) on its approach side, at the gate's height,
    drones 0.4 m apart: every drone is within reach of a gate's frame bars, so the kernel's
    "no drone near a gate" shortcut never applies (the worst case for it; a race is in between)."""
    g = torch.as_tensor(track.gate_array(), dtype=torch.float32)[torch.arange(worlds) % len(track.gates)]  # (W, 4)
    n = torch.stack([torch.cos(g[:, 3]), torch.sin(g[:, 3]), torch.zeros(worlds)], -1)        # (W, 3)
    side = torch.stack([-torch.sin(g[:, 3]), torch.cos(g[:, 3]), torch.zeros(worlds)], -1)    # (W, 3)
    offsets = (torch.arange(drones, dtype=torch.float32) - (drones - 1) / 2.0) * 0.4          # (D,)
    return g[:, None, :3] + 0.6 * n[:, None] + offsets[None, :, None] * side[:, None]


SCENARIOS = {"hover": hover_start, "gates": gates_start}
MODES = ("c", "eager", "compiled")  #: fused C kernel, torch eager, torch.compile


def available_modes(compile: bool, drones: int = 1) -> list[str]:
    """Simulator modes to measure: the fused C kernel when it builds here and takes ``drones`` per
    world, torch eager always, torch.compile when asked."""
    c = ckernel.available() and drones <= ckernel.MAX_DRONES
    return (["c"] if c else []) + ["eager"] + (["compiled"] if compile else [])


def check_scenario(scenario: str) -> None:
    """ConfigError (one line) unless ``scenario`` is one of SCENARIOS."""
    if scenario not in SCENARIOS:
        raise ConfigError(f"unknown scenario {scenario!r} (known: {', '.join(SCENARIOS)})")


def measure_sim(worlds: int, drones: int, *, mode: str, steps: int, warmup: int, substeps: int,
                track: str, profile: str, repeats: int = 3, scenario: str = "hover") -> dict:
    """Time ``repeats`` x ``steps`` calls of Simulator.step(hover thrust, zero rates, substeps) after
    ``warmup`` calls; the rate is that of the fastest repeat (the median is kept too).
    mode: "c" (fused C kernel), "eager" (torch) or "compiled" (torch.compile)."""
    if mode not in MODES:
        raise ConfigError(f"unknown simulator mode {mode!r} (known: {', '.join(MODES)})")
    trk, prof = load_track(track), load_profile(profile)
    sim = Simulator(trk, prof, worlds, drones, obstacles=True, compile=mode == "compiled",
                    backend="c" if mode == "c" else "torch")
    check_scenario(scenario)
    sim.reset(torch.arange(worlds), SCENARIOS[scenario](trk, worlds, drones))
    thrust = torch.full((worlds, drones), prof.weight)                  # (W, D) N, hover
    rates = torch.zeros(worlds, drones, 3)                               # (W, D, 3) rad/s
    t0 = time.perf_counter()
    for _ in range(warmup):
        sim.step(thrust, rates, substeps)
    warm = time.perf_counter() - t0
    walls, cpus = [], []
    for _ in range(repeats):  # best of `repeats`: the machine may be shared
        cpu0, t0 = time.process_time(), time.perf_counter()
        for _ in range(steps):
            sim.step(thrust, rates, substeps)
        walls.append(time.perf_counter() - t0)
        cpus.append(time.process_time() - cpu0)
    drone_steps = worlds * drones * substeps * steps
    best = min(range(repeats), key=walls.__getitem__)
    return {"worlds": worlds, "drones": drones, "total_drones": worlds * drones, "mode": mode,
            "drone_steps_per_s": drone_steps / walls[best],
            "median_drone_steps_per_s": drone_steps / sorted(walls)[len(walls) // 2],
            "seconds": walls, "policy_steps": steps, "substeps": substeps, "repeats": repeats, "warmup_s": warm,
            "cpu_per_wall": cpus[best] / walls[best], "crashed_fraction": float(sim.crashed.float().mean()),
            "mean_z_m": float(sim.pos[..., 2].mean()), "scenario": scenario, "kernel": _kernel_name() if mode == "c" else None}


def _kernel_name() -> str | None:
    """File name of the loaded C kernel (its name carries the hash of its source and flags)."""
    lib = getattr(ckernel, "_lib", None)
    return Path(lib._name).name if lib is not None else None


def peer_python(explicit: Optional[Path]) -> Optional[Path]:
    """--peer-python, else $CFRACE_PEER_PYTHON, else None (no peer)."""
    if explicit is not None:
        return explicit
    env = os.environ.get("CFRACE_PEER_PYTHON")
    return Path(env) if env else None


def run_peer(python: Path, totals: list[int], per_world: int, calls: int, threads: int, timeout: float) -> dict:
    """Run benchmarks/crazyflow_peer.py with the peer's python; returns its JSON document."""
    script = ROOT / "benchmarks" / "crazyflow_peer.py"
    if not script.exists():
        raise ConfigError(f"{script}: peer benchmark script not found")
    if not python.exists():
        raise ConfigError(f"{python}: peer python not found (set --peer-python or CFRACE_PEER_PYTHON)")
    env = dict(os.environ)
    if threads > 0:  # same thread budget as the torch side
        env["XLA_FLAGS"] = (env.get("XLA_FLAGS", "") + f" --xla_cpu_multi_thread_eigen={'true' if threads > 1 else 'false'}"
                            f" intra_op_parallelism_threads={threads}").strip()
    cmd = [str(python), str(script), "--drones", ",".join(map(str, totals)), "--per-world", str(per_world),
           "--calls", str(calls)]
    with tempfile.TemporaryDirectory() as cwd:  # MuJoCo may drop a log file into the working directory
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True, cwd=cwd, env=env, timeout=timeout)
        except subprocess.TimeoutExpired:
            raise CfraceError(f"peer benchmark {script.name} timed out after {timeout:.0f} s") from None
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("{")]
    if proc.returncode != 0 or not lines:
        tail = (proc.stderr.strip().splitlines() or ["no output"])[-1]
        raise CfraceError(f"peer benchmark failed (exit {proc.returncode}) with {python}: {tail}")
    doc = json.loads(lines[-1])
    doc["command"] = " ".join(cmd)
    return doc


def machine_info(threads: int) -> dict:
    model = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    sim_dir = ROOT / "cfrace" / "sim"
    digest = hashlib.sha256(b"".join(p.read_bytes() for p in sorted(sim_dir.glob("*.[pc]*")) if p.is_file()))
    try:
        git = subprocess.run(["git", "-C", str(ROOT), "describe", "--always", "--dirty"], capture_output=True,
                             text=True, timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        git = ""
    return {"cpu": model, "cores": os.cpu_count(), "torch": torch.__version__,
            "cfrace_git": git, "sim_sources_sha256": digest.hexdigest()[:16], "torch_threads": torch.get_num_threads(),
            "threads_option": threads, "python": platform.python_version(), "platform": platform.platform(),
            "loadavg_start": list(os.getloadavg()), "date": datetime.now(timezone.utc).isoformat(timespec="seconds")}


def rate_text(x: Optional[float]) -> str:
    if x is None or not math.isfinite(x):
        return "-"
    return f"{x / 1e6:.2f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"


def summarize(results: list[dict], peer: list[dict]) -> list[dict]:
    """Per size: the rate of each mode, the best cfrace rate, crazyflow's and the ratio best/crazyflow."""
    rows = []
    for w, d in dict.fromkeys((r["worlds"], r["drones"]) for r in results):
        by_mode = {r["mode"]: r["drone_steps_per_s"] for r in results if (r["worlds"], r["drones"]) == (w, d)}
        best_mode = max(by_mode, key=by_mode.get)
        cf = next((p["drone_steps_per_s"] for p in peer if p["total_drones"] == w * d), None)
        rows.append({"worlds": w, "drones": d, "total_drones": w * d, **{m: by_mode.get(m) for m in MODES},
                     "best": by_mode[best_mode], "best_mode": best_mode,
                     "crazyflow": cf, "ratio": by_mode[best_mode] / cf if cf else None})
    return rows


def choose_modes(compile: bool, modes: str = "", drones: int = 1) -> list[str]:
    """The modes to measure with ``drones`` per world: ``modes`` (comma-separated subset of MODES)
    or every available one."""
    if not modes:
        return available_modes(compile, drones)
    wanted = [m.strip() for m in modes.split(",") if m.strip()]
    unknown = [m for m in wanted if m not in MODES]
    if unknown or not wanted:
        raise ConfigError(f"--modes: expected a subset of {','.join(MODES)}, got {modes!r}")
    if "c" in wanted and drones > ckernel.MAX_DRONES:
        raise ConfigError(f"--modes c: the C kernel takes at most {ckernel.MAX_DRONES} drones per world, "
                          f"not --drones {drones} (measure eager or compiled)")
    missing = [m for m in wanted if m not in available_modes(True)]
    if missing:
        raise ConfigError(f"--modes: {', '.join(missing)} not available on this machine")
    return wanted


def checked_modes(compile: bool, modes: str, drones: int, scenario: str, track: str, profile: str) -> list[str]:
    """The modes `cfrace bench sim` measures, once its input holds up (else a one-line ConfigError,
    before anything is printed): the scenario, track, profile and ``modes`` (default, about a minute:
    the C kernel if it takes ``drones`` per world, else eager; compiled too with ``compile``)."""
    check_scenario(scenario)
    load_track(track), load_profile(profile)
    if not modes:
        avail = choose_modes(compile, drones=drones)
        modes = ",".join(["c" if "c" in avail else "eager", *(["compiled"] if "compiled" in avail else [])])
    return choose_modes(compile, modes, drones)


def measure_all(sizes: list[int], drones: int, modes: list[str], say: Callable[[str], None], **measure) -> tuple:
    """measure_sim for every size and mode -> (results, errors by mode). A mode other than eager
    that fails (torch.compile without a compiler, ...) is reported and skipped."""
    results, errors = [], {}
    for w in sizes:
        for mode in modes:
            if mode in errors:
                continue
            try:
                r = measure_sim(w, drones, mode=mode, **measure)
            except CfraceError:
                raise
            except Exception as exc:  # noqa: BLE001 - report, keep the others
                if mode == "eager":
                    raise
                errors[mode] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                say(f"[yellow]{mode} unavailable: {errors[mode]}[/yellow]")
                continue
            results.append(r)
            say(f"  {w:>5} worlds x {drones} drones, {r['mode']:>8}: {rate_text(r['drone_steps_per_s'])} "
                f"drone-steps/s (warm-up {r['warmup_s']:.1f} s, crashed {r['crashed_fraction']:.0%})")
    return results, errors


def measure_peer(peer: Optional[bool], python: Optional[Path], sizes: list[int], drones: int, calls: int,
                 threads: int, say: Callable[[str], None]) -> Optional[dict]:
    """The crazyflow peer's JSON document, or None when it is off, not found or (unless asked for
    with peer=True) failed."""
    if peer is True and python is None:
        raise ConfigError("--peer: no peer python (give --peer-python or set CFRACE_PEER_PYTHON)")
    if peer is False or python is None:
        return None
    totals = sorted({w * drones for w in sizes})
    say(f"running crazyflow peer with {python} on {totals} drones ...")
    try:
        return run_peer(python, totals, drones, calls, threads, timeout=3600)
    except CfraceError as exc:
        if peer is True:
            raise
        say(f"[yellow]peer skipped: {exc}[/yellow]")
        return None


def bench_doc(results: list, peer_doc: Optional[dict], rows: list, machine: dict, errors: dict) -> dict:
    """The JSON document of `cfrace bench sim --json`."""
    return {"results": results, "peer": (peer_doc or {}).get("results", []), "summary": rows, "machine": machine,
            "errors": errors, "peer_info": {k: v for k, v in (peer_doc or {}).items() if k != "results"}}
