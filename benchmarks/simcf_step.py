"""What one step of the simulated Crazyflies' physics costs (simcf: one world, two drones).

    python benchmarks/simcf_step.py [--backends c,torch] [--steps 3000] [--json F]

Times SimFleet.advance(0.01) (one 10 ms control chunk: the firmware logic, then 5 physics steps of
2 ms) for each backend of cfrace.simcf.physics.make_physics, with hovering commands, one thread.
Prints us per 10 ms chunk (p50, p99) and per physics step. Run the same script against another
checkout (PYTHONPATH=SRC) to compare versions; backends a version does not have are skipped.
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time


def measure(backend: str, chunks: int) -> dict | None:
    import torch

    from cfrace.errors import ConfigError
    from cfrace.simcf.firmware import SimFleet

    torch.set_num_threads(1)
    try:
        fleet = SimFleet("lemniscate", "cf2x_paper", 2, backend=backend, arming_required=False, obstacles=False)
    except ConfigError:
        return None
    for i in range(2):
        fleet.set_param(i, "flightmode.stabModeRoll", 0)
        fleet.set_param(i, "flightmode.stabModePitch", 0)
        fleet.handle_setpoint(i, 0.0, 0.0, 0.0, 0)
    times = []
    for k in range(chunks + 50):
        for i in range(2):
            fleet.handle_setpoint(i, 0.0, 0.0, 0.0, 38000)
        t0 = time.perf_counter()
        fleet.advance(0.01)
        if k >= 50:   # warm-up chunks not counted
            times.append((time.perf_counter() - t0) * 1e6)
    times.sort()
    p50, p99 = statistics.median(times), times[int(0.99 * (len(times) - 1))]
    return {"backend": fleet.backend, "chunk_us_p50": round(p50, 1), "chunk_us_p99": round(p99, 1),
            "step_us_p50": round(p50 / 5, 1)}


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--backends", default="c,torch,numpy")
    ap.add_argument("--chunks", type=int, default=2000)
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows = []
    for b in args.backends.split(","):
        r = measure(b, args.chunks if b != "torch" else max(50, args.chunks // 10))
        if r is None:
            print(f"{b}: not in this version")
            continue
        rows.append(r)
        print(f"{b}: {r['chunk_us_p50']:.1f} us p50 / {r['chunk_us_p99']:.1f} us p99 per 10 ms chunk "
              f"({r['step_us_p50']:.1f} us per 2 ms physics step)", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    return 0


if __name__ == "__main__":
    sys.exit(main())
