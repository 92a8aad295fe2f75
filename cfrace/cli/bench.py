"""`cfrace bench ...`: benchmarks that print figures. Other CLI modules add commands to `bench_app`.

`cfrace bench sim` measures the batched simulator in drone-steps per second: one drone advanced by
one 2 ms physics step with the full model (motors, rate PID, drag, floor, arena, gate frames and
gate passing, obstacles, drone-drone contacts) with each backend (fused C kernel, torch eager,
torch.compile), and runs the crazyflow
simulator (JAX, benchmarks/crazyflow_peer.py, in its own venv) on the same numbers of drones.
"""

from __future__ import annotations

import json
import math
import os
import platform
import subprocess
import tempfile
import time
from datetime import datetime, timezone
from pathlib import Path
from typing import Optional

import typer
from rich.console import Console
from rich.table import Table

from cfrace.errors import CfraceError, ConfigError

bench_app = typer.Typer(help="Benchmarks that print figures (speed, latency).", no_args_is_help=True)
console = Console()

DEFAULT_PEER_PYTHON = Path("/work/peers/venv/bin/python")


# ------------------------------------------------------------------------------------- measuring

def hover_start(track, worlds: int, drones: int):
    """(W, D, 3) start positions: 1.5 m before gate 0 on its approach side, drones 0.5 m apart."""
    import torch

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
    import torch

    g = torch.as_tensor(track.gate_array(), dtype=torch.float32)[torch.arange(worlds) % len(track.gates)]  # (W, 4)
    n = torch.stack([torch.cos(g[:, 3]), torch.sin(g[:, 3]), torch.zeros(worlds)], -1)        # (W, 3)
    side = torch.stack([-torch.sin(g[:, 3]), torch.cos(g[:, 3]), torch.zeros(worlds)], -1)    # (W, 3)
    offsets = (torch.arange(drones, dtype=torch.float32) - (drones - 1) / 2.0) * 0.4          # (D,)
    return g[:, None, :3] + 0.6 * n[:, None] + offsets[None, :, None] * side[:, None]


SCENARIOS = {"hover": hover_start, "gates": gates_start}
MODES = ("c", "eager", "compiled")  #: fused C kernel, torch eager, torch.compile


def available_modes(compile: bool) -> list[str]:
    """Simulator modes to measure: the fused C kernel when the simulator has one and it builds here,
    torch eager always, torch.compile when asked."""
    import inspect

    from cfrace.sim import simulator

    modes = []
    if "backend" in inspect.signature(simulator.Simulator).parameters:
        try:
            from cfrace.sim import ckernel

            if ckernel.available():
                modes.append("c")
        except ImportError:
            pass
    return modes + ["eager"] + (["compiled"] if compile else [])


def measure_sim(worlds: int, drones: int, *, mode: str, steps: int, warmup: int, substeps: int,
                track: str, profile: str, repeats: int = 3, scenario: str = "hover") -> dict:
    """Time ``repeats`` x ``steps`` calls of Simulator.step(hover thrust, zero rates, substeps) after
    ``warmup`` calls; the rate is that of the fastest repeat (the median is kept too).
    mode: "c" (fused C kernel), "eager" (torch) or "compiled" (torch.compile)."""
    import inspect

    import torch

    from cfrace.drone import load_profile
    from cfrace.sim.simulator import Simulator
    from cfrace.track import load_track

    if mode not in MODES:
        raise ConfigError(f"unknown simulator mode {mode!r} (known: {', '.join(MODES)})")
    trk, prof = load_track(track), load_profile(profile)
    kwargs = {"compile": mode == "compiled"}
    if "backend" in inspect.signature(Simulator).parameters:
        kwargs["backend"] = "c" if mode == "c" else "torch"
    sim = Simulator(trk, prof, worlds, drones, obstacles=True, **kwargs)
    if scenario not in SCENARIOS:
        raise ConfigError(f"unknown scenario {scenario!r} (known: {', '.join(SCENARIOS)})")
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
    try:
        from cfrace.sim import ckernel

        lib = getattr(ckernel, "_lib", None)
        return Path(lib._name).name if lib is not None else None
    except ImportError:
        return None


def peer_python(explicit: Optional[Path]) -> Optional[Path]:
    """--peer-python, else $CFRACE_PEER_PYTHON, else /work/peers/venv/bin/python if it exists."""
    if explicit is not None:
        return explicit
    env = os.environ.get("CFRACE_PEER_PYTHON")
    if env:
        return Path(env)
    return DEFAULT_PEER_PYTHON if DEFAULT_PEER_PYTHON.exists() else None


def run_peer(python: Path, totals: list[int], per_world: int, calls: int, threads: int, timeout: float) -> dict:
    """Run benchmarks/crazyflow_peer.py with the peer's python; returns its JSON document."""
    from cfrace.paths import ROOT

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
    import torch

    model = platform.processor()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                model = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    import hashlib

    from cfrace.paths import ROOT

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


# ------------------------------------------------------------------------------------- reporting

def _rate(x: Optional[float]) -> str:
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


def summary_table(rows: list[dict]) -> Table:
    table = Table(title="simulator speed: drone-steps per second (one drone, one 2 ms step)")
    modes = [m for m in MODES if any(r[m] is not None for r in rows)]
    for col in ("worlds", "x drones", "= drones", *[f"cfrace {m}" for m in modes], "cfrace best",
                "crazyflow", "cfrace/crazyflow"):
        table.add_column(col, justify="right")
    for r in rows:
        ratio = "-" if r["ratio"] is None else f"{r['ratio']:.2f}x"
        table.add_row(str(r["worlds"]), str(r["drones"]), str(r["total_drones"]), *[_rate(r[m]) for m in modes],
                      _rate(r["best"]), _rate(r["crazyflow"]), ratio)
    return table


def _ints(text: str, what: str) -> list[int]:
    try:
        values = [int(v) for v in text.split(",") if v.strip()]
    except ValueError:
        raise ConfigError(f"--{what}: expected comma-separated integers, got {text!r}") from None
    if not values or any(v < 1 for v in values):
        raise ConfigError(f"--{what}: expected positive integers, got {text!r}")
    return values


@bench_app.command("sim")
def sim_cmd(
    worlds: str = typer.Option("1,64,1024,2048,4096", help="comma-separated world counts"),
    drones: int = typer.Option(2, min=1, help="drones per world"),
    steps: int = typer.Option(30, min=1, help="timed policy steps (each `substeps` physics steps)"),
    warmup: int = typer.Option(3, min=1, help="untimed policy steps first (torch.compile compiles here)"),
    repeats: int = typer.Option(3, min=1, help="timed repeats per size and mode; the fastest counts"),
    substeps: int = typer.Option(10, min=1, help="physics steps of 2 ms per policy step"),
    compile: bool = typer.Option(True, "--compile/--no-compile", help="also measure torch.compile"),
    modes_opt: str = typer.Option("", "--modes", help="comma-separated subset of c,eager,compiled "
                                  "(default: c if built, eager, compiled with --compile)"),
    peer: Optional[bool] = typer.Option(None, "--peer/--no-peer",
                                        help="run the crazyflow peer (default: when a peer python is found)"),
    peer_python_path: Optional[Path] = typer.Option(None, "--peer-python", help="python of the crazyflow venv"),
    peer_calls: int = typer.Option(3, min=1, help="timed sim.step(1000) calls per size on the peer; the fastest counts"),
    threads: int = typer.Option(0, min=0, help="CPU threads for torch (and XLA); 0 keeps the defaults"),
    track: str = typer.Option("complex", help="track name or path"),
    profile: str = typer.Option("cf2x_paper", help="drone profile name or path"),
    scenario: str = typer.Option("hover", help="hover: drones 1.5 m before gate 0 | gates: every drone "
                                 "0.6 m before a gate, within reach of its frame bars"),
    json_out: Optional[Path] = typer.Option(None, "--json", help="also write all numbers to this JSON file"),
) -> None:
    """Simulator drone-steps per second for each world count (C kernel, torch eager, torch.compile)
    against crazyflow."""
    import torch

    sizes = _ints(worlds, "worlds")
    if threads > 0:
        torch.set_num_threads(threads)
    machine = machine_info(threads)
    console.print(f"[bold]cfrace bench sim[/bold] on {machine['cpu']} ({machine['cores']} cores, torch "
                  f"{machine['torch']}, {machine['torch_threads']} threads), load average "
                  f"{machine['loadavg_start'][0]:.2f}")
    modes = available_modes(compile)
    if modes_opt:
        wanted = [m.strip() for m in modes_opt.split(",") if m.strip()]
        unknown = [m for m in wanted if m not in MODES]
        if unknown or not wanted:
            raise ConfigError(f"--modes: expected a subset of {','.join(MODES)}, got {modes_opt!r}")
        missing = [m for m in wanted if m not in available_modes(True)]
        if missing:
            raise ConfigError(f"--modes: {', '.join(missing)} not available on this machine")
        modes = wanted
    console.print(f"modes: {', '.join(modes)}")
    results, errors = [], {}
    for w in sizes:
        for mode in modes:
            if mode in errors:
                continue
            try:
                r = measure_sim(w, drones, mode=mode, steps=steps, warmup=warmup, substeps=substeps,
                                track=track, profile=profile, repeats=repeats, scenario=scenario)
            except CfraceError:
                raise
            except Exception as exc:  # torch.compile missing a compiler, etc.: report, keep the others
                if mode == "eager":
                    raise
                errors[mode] = f"{type(exc).__name__}: {str(exc).splitlines()[0] if str(exc) else ''}"
                console.print(f"[yellow]{mode} unavailable: {errors[mode]}[/yellow]")
                continue
            results.append(r)
            console.print(f"  {w:>5} worlds x {drones} drones, {r['mode']:>8}: {_rate(r['drone_steps_per_s'])} "
                          f"drone-steps/s (warm-up {r['warmup_s']:.1f} s, crashed {r['crashed_fraction']:.0%})")
    peer_doc, peer_rows = None, []
    py = peer_python(peer_python_path)
    if peer is True and py is None:
        raise ConfigError("--peer: no peer python (give --peer-python or set CFRACE_PEER_PYTHON)")
    if peer is not False and py is not None:
        totals = sorted({w * drones for w in sizes})
        console.print(f"running crazyflow peer with {py} on {totals} drones ...")
        try:
            peer_doc = run_peer(py, totals, drones, peer_calls, threads, timeout=3600)
            peer_rows = peer_doc["results"]
        except CfraceError as exc:
            if peer is True:
                raise
            console.print(f"[yellow]peer skipped: {exc}[/yellow]")
    machine["loadavg_end"] = list(os.getloadavg())
    rows = summarize(results, peer_rows)
    console.print(summary_table(rows))
    if peer_doc:
        console.print(f"crazyflow {peer_doc['versions'].get('crazyflow')} (jax {peer_doc['versions'].get('jax')}): "
                      "first_principles + attitude control, 500 Hz, sim.step(1000) jitted; no collision checks")
    console.print(f"load average at start {machine['loadavg_start'][0]:.2f}, at end {machine['loadavg_end'][0]:.2f}")
    if json_out is not None:
        doc = {"results": results, "peer": peer_rows, "summary": rows, "machine": machine, "errors": errors,
               "peer_info": {k: v for k, v in (peer_doc or {}).items() if k != "results"}}
        json_out.parent.mkdir(parents=True, exist_ok=True)
        json_out.write_text(json.dumps(doc, indent=2))
        console.print(f"wrote {json_out}")


def register(app: typer.Typer) -> None:
    """Add the bench group to the top-level app."""
    app.add_typer(bench_app, name="bench")
