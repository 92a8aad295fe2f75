"""The flight loop's timing with and without the warm-up window, side by side, interleaved.

    python benchmarks/loop_warmup_ab.py [--leads 0,1,3,5] [--rounds 3] [--seconds 8]
                                        [--policies paper|shipped] [--json FILE]

Runs `cfrace bench loop` (cfrace.flight.benchloop.bench_loop: the unchanged fly code against a
`cfrace sim serve` process, real cflib over UDP, flight log on) once per warm-up window per round,
the windows interleaved within each round so that a change in the machine's load hits all of them
alike. Prints per window the median over the rounds of each figure (ms), the figure's spread
(min..max over rounds) for the p99s, the goals met in how many rounds, and the ratio of each median
to the no-warm-up run's (window 0). Used for docs/benchmarks.md ("Warm-up window").
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from cfrace.flight.benchloop import GOALS_MS, bench_loop

FIGURES = [("compute p50", lambda l: l["compute_ms"]["p50"]),
           ("compute p99", lambda l: l["compute_ms"]["p99"]),
           ("compute CPU p99", lambda l: l["compute_cpu_ms"]["p99"]),
           ("inference p50", lambda l: max(v["p50"] for v in l["inference_ms"].values())),
           ("inference p99", lambda l: l["inference_p99_ms"]),
           ("jitter p99", lambda l: l["period_jitter_p99_ms"]),
           ("warm-up CPU / tick p50", lambda l: l["prewarm_ms"]["p50"] or 0.0),
           ("warm-up passes / tick", lambda l: l.get("prewarm_calls_mean") or 0.0)]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--leads", default="0,1,3,5", help="warm-up windows in ms, comma-separated (0 = off)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--policies", default="paper", choices=["paper", "shipped"])
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    leads = [float(x) for x in args.leads.split(",")]
    runs: dict[float, list[dict]] = {ms: [] for ms in leads}
    t0 = time.strftime("%Y-%m-%d %H:%M:%S")
    for r in range(args.rounds):
        for ms in leads:
            res = bench_loop(args.seconds, policies=args.policies, prewarm_s=ms / 1e3)
            runs[ms].append(res)
            loop = res["loop"]
            print(f"round {r + 1} window {ms:g} ms: compute {loop['compute_ms']['p50']:.3f} / "
                  f"{loop['compute_ms']['p99']:.3f}, inference p99 {loop['inference_p99_ms']:.3f}, "
                  f"jitter p99 {loop['period_jitter_p99_ms']:.3f} ms (load {res['load_avg'][0]:.2f})", flush=True)
    print(f"\n{args.policies} actors, {args.rounds} rounds of {args.seconds:g} s per window, {t0} .. "
          f"{time.strftime('%H:%M:%S')}, {os.cpu_count()} CPUs; medians over rounds, ms")
    base = {name: float(np.median([f(x["loop"]) for x in runs[leads[0]]])) for name, f in FIGURES}
    head = f"{'window':>8s} " + " ".join(f"{name:>22s}" for name, _ in FIGURES) + "   goals met (compute, jitter, inference)"
    print(head)
    table = {}
    for ms in leads:
        cells, row = [], {}
        for name, f in FIGURES:
            vals = [f(x["loop"]) for x in runs[ms]]
            med = float(np.median(vals))
            row[name] = {"median": med, "min": float(min(vals)), "max": float(max(vals))}
            ratio = f" x{med / base[name]:.2f}" if base[name] and ms != leads[0] and "warm" not in name else ""
            spread = f" ({min(vals):.2f}..{max(vals):.2f})" if "p99" in name else ""
            cells.append(f"{med:.3f}{spread}{ratio}".rjust(22))
        met = [sum(bool(x["goals_met"][k]) for x in runs[ms]) for k in GOALS_MS]
        row["goals_met_rounds"] = dict(zip(GOALS_MS, met))
        table[ms] = row
        print(f"{ms:>6g}ms " + " ".join(cells) + f"   {met[0]}/{len(runs[ms])}, {met[1]}/{len(runs[ms])}, "
              f"{met[2]}/{len(runs[ms])}")
    if args.json:
        with open(args.json, "w") as fh:
            json.dump({"policies": args.policies, "rounds": args.rounds, "seconds": args.seconds, "start": t0,
                       "table_ms": {str(k): v for k, v in table.items()}, "goals_ms": GOALS_MS,
                       "runs": {str(k): [{"loop": x["loop"], "load_avg": x["load_avg"], "time": x["time"]} for x in v]
                                for k, v in runs.items()}}, fh, indent=1, default=str)


if __name__ == "__main__":
    main()
