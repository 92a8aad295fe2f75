"""Does a sweep on Ray use the cores? One single-thread training run alone, then two at once.

Each run is `cfrace.rl.train.bench_train` (whole training iterations: simulation, inference,
update, one torch thread) in a Ray task of one CPU; the figure is the two runs' env steps/s added
up over the one run's, measured one after the other in the same call. The machine's load and the
processes that used the most CPU meanwhile are recorded with it (the development machine is shared).
"""

from __future__ import annotations

import os
import tempfile
import time
from pathlib import Path


def _bench_task(method: str, track: str, envs: int | None, iterations: int) -> dict:
    from cfrace.rl.train import bench_train

    return bench_train(method, track, False, "cpu", envs, iterations, "cpu", threads=1)


def machine_load() -> str:
    """`uptime`-like: the 1/5/15-min load averages and the core count."""
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores"


def cpu_times() -> dict[int, tuple[float, str]]:
    """pid -> (CPU seconds used so far, command line) of every process (Linux /proc)."""
    tick = os.sysconf("SC_CLK_TCK")
    out = {}
    for d in os.listdir("/proc"):
        if not d.isdigit():
            continue
        try:
            with open(f"/proc/{d}/stat") as fh:
                fields = fh.read().rsplit(")", 1)[1].split()
            with open(f"/proc/{d}/cmdline", "rb") as fh:
                cmd = fh.read().replace(b"\0", b" ").decode(errors="replace").strip()
        except OSError:
            continue
        out[int(d)] = ((int(fields[11]) + int(fields[12])) / tick, cmd)
    return out


def busy_processes(before: dict, after: dict, wall_s: float, n: int = 8) -> list[str]:
    """The n processes that used the most CPU between two cpu_times() snapshots ``wall_s`` apart:
    "pid  %CPU of one core over the interval  command"."""
    used = [(after[p][0] - before.get(p, (0.0, ""))[0], p, after[p][1]) for p in after]
    used.sort(reverse=True)
    return [f"{p:>7} {100 * cpu / max(wall_s, 1e-9):5.0f}%  {cmd[:120]}" for cpu, p, cmd in used[:n] if cpu > 0]


def bench_parallel(method: str = "ds", track: str = "lemniscate", envs: int | None = None, iterations: int = 3,
                   address: str | None = None) -> dict:
    """Env steps/s of one run alone and of two runs at once, each a one-CPU Ray task."""
    from cfrace.sweep.ray_exec import init_ray

    t_init = time.perf_counter()
    ray = init_ray(address, None if address else 2)
    ray_start_s = time.perf_counter() - t_init
    task = ray.remote(num_cpus=1, max_retries=0)(_bench_task)
    ray.get([task.remote(method, track, 8, 1), task.remote(method, track, 8, 1)])  # warm both workers
    load_before = machine_load()
    t0 = time.perf_counter()
    alone = ray.get(task.remote(method, track, envs, iterations))
    t1 = time.perf_counter()
    snap = cpu_times()
    pair = ray.get([task.remote(method, track, envs, iterations) for _ in range(2)])
    t2 = time.perf_counter()
    busy = busy_processes(snap, cpu_times(), t2 - t1)
    rates = [p["env_steps_per_s"] for p in pair]
    # CPU cores each run got while timed: wall rate / rate per CPU second of its process
    cores = lambda r: r["env_steps_per_s"] / r["env_steps_per_cpu_s"] if "env_steps_per_cpu_s" in r else None
    return {"method": method, "track": track, "num_envs": alone["num_envs"], "iterations": iterations,
            "threads_per_run": 1, "alone_env_steps_per_s": alone["env_steps_per_s"],
            "pair_env_steps_per_s": rates, "pair_total_env_steps_per_s": sum(rates),
            "speedup": sum(rates) / alone["env_steps_per_s"], "alone_wall_s": t1 - t0, "pair_wall_s": t2 - t1,
            "alone_shares": {k: alone[k] for k in alone if k.startswith("share_")},
            "alone_env_steps_per_cpu_s": alone.get("env_steps_per_cpu_s"),
            "pair_env_steps_per_cpu_s": [p.get("env_steps_per_cpu_s") for p in pair],
            "alone_cores": cores(alone), "pair_cores": [cores(p) for p in pair],
            "load_before": load_before, "load_after": machine_load(), "busy_processes": busy,
            "cpu_count": os.cpu_count(), "ray_start_s": ray_start_s,
            "ray": "cluster " + address if address else "local instance, 2 CPUs"}


def bench_sweep_wall(spec: str | Path, address: str | None = None) -> dict:
    """Wall time of a whole sweep file run one run after another (run_local) and on Ray (run_ray),
    each into a fresh temporary output root, the same call; with the machine's load. The Ray time
    does not include starting Ray (bench_parallel reports that as ray_start_s)."""
    from cfrace.sweep.local import run_local
    from cfrace.sweep.ray_exec import run_ray
    from cfrace.sweep.parse import load_spec

    sweep = load_spec(spec)
    with tempfile.TemporaryDirectory(prefix="cfrace-bench-sweep-") as tmp:
        load_before = machine_load()
        snap = cpu_times()
        t0 = time.perf_counter()
        run_local(sweep, Path(tmp) / "sequential", echo=lambda s: None, log_dir=True)
        sequential = time.perf_counter() - t0
        t1 = time.perf_counter()
        report = run_ray(sweep, Path(tmp) / "ray", address, None if address else os.cpu_count())
        on_ray = time.perf_counter() - t1
        busy = busy_processes(snap, cpu_times(), on_ray + sequential)
        if not report.ok:
            raise RuntimeError(f"sweep failed on Ray: {report.failed + report.blocked}")
    return {"spec": str(spec), "runs": len(sweep.runs), "sequential_wall_s": sequential, "ray_wall_s": on_ray,
            "ray_run_wall_s_sum": report.run_wall_s, "speedup": sequential / on_ray, "load_before": load_before,
            "load_after": machine_load(), "busy_processes": busy}
