"""Does a sweep on Ray use the cores? One single-thread training run alone, then two at once.

Each run is `cfrace.rl.train.bench_train` (whole training iterations: simulation, inference,
update, one torch thread) in a Ray task of one CPU; the figure is the two runs' env steps/s added
up over the one run's, measured one after the other in the same call. The machine's load and its
busiest processes are recorded with it (the development machine is shared).
"""

from __future__ import annotations

import os
import subprocess
import time


def _bench_task(method: str, track: str, envs: int | None, iterations: int) -> dict:
    from cfrace.rl.train import bench_train

    return bench_train(method, track, False, "cpu", envs, iterations, "cpu", threads=1)


def machine_load() -> str:
    """`uptime`-like: the 1/5/15-min load averages and the core count."""
    one, five, fifteen = os.getloadavg()
    return f"load average {one:.2f} {five:.2f} {fifteen:.2f} on {os.cpu_count()} cores"


def busy_processes(n: int = 8) -> list[str]:
    """The n processes with the most CPU (ps: pid, %cpu since start, elapsed, command)."""
    try:
        out = subprocess.run(["ps", "-eo", "pid,pcpu,etime,args", "--sort=-pcpu"], capture_output=True, text=True,
                             timeout=10).stdout.splitlines()
    except (OSError, subprocess.SubprocessError):
        return []
    return [line[:140] for line in out[: n + 1]]


def bench_parallel(method: str = "ds", track: str = "lemniscate", envs: int | None = None, iterations: int = 3,
                   address: str | None = None) -> dict:
    """Env steps/s of one run alone and of two runs at once, each a one-CPU Ray task."""
    from cfrace.sweep.ray_exec import init_ray

    ray = init_ray(address, None if address else 2)
    task = ray.remote(num_cpus=1, max_retries=0)(_bench_task)
    ray.get([task.remote(method, track, 8, 1), task.remote(method, track, 8, 1)])  # warm both workers
    load_before = machine_load()
    t0 = time.perf_counter()
    alone = ray.get(task.remote(method, track, envs, iterations))
    t1 = time.perf_counter()
    busy = busy_processes()
    pair = ray.get([task.remote(method, track, envs, iterations) for _ in range(2)])
    t2 = time.perf_counter()
    rates = [p["env_steps_per_s"] for p in pair]
    return {"method": method, "track": track, "num_envs": alone["num_envs"], "iterations": iterations,
            "threads_per_run": 1, "alone_env_steps_per_s": alone["env_steps_per_s"],
            "pair_env_steps_per_s": rates, "pair_total_env_steps_per_s": sum(rates),
            "speedup": sum(rates) / alone["env_steps_per_s"], "alone_wall_s": t1 - t0, "pair_wall_s": t2 - t1,
            "alone_shares": {k: alone[k] for k in alone if k.startswith("share_")},
            "load_before": load_before, "load_after": machine_load(), "busy_processes": busy,
            "cpu_count": os.cpu_count(), "ray": "cluster " + address if address else "local instance, 2 CPUs"}
