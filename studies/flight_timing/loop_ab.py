"""The flight loop's timing under several settings, side by side, interleaved.

    python studies/flight_timing/loop_ab.py [--configs NAME:KEY=V,...;NAME:...] [--rounds 3] [--seconds 8]
                                 [--policies paper|shipped] [--json FILE]

Runs `cfrace bench loop` (cfrace.rehearsal.loop_timing.bench_loop: the unchanged fly code against a
`cfrace sim serve` process, real cflib over UDP, flight log on) once per setting per round, the
settings interleaved within each round so that a change in the machine's load hits all of them
alike. KEYs: prewarm_ms, loop_cpu (auto/off/N), rt_priority (auto/0/N). Prints per setting the median over the
rounds of each figure (ms), the spread (min..max over rounds) of the p99s, the goals met in how many
rounds, and the ratio of each median to the first setting's. Unset keys take bench_loop's defaults
(the flight defaults: loop_cpu auto, rt_priority auto, 3-ms window). Default settings: the loop
thread unpinned at normal priority, pinned to a CPU of its own, and the default (pinned, SCHED_FIFO
where permitted) (docs/benchmarks.md, "Loop CPU and priority"); studies/flight_timing/loop_warmup_ab.py compares warm-up
windows with it.
"""

from __future__ import annotations

import argparse
import json
import os
import time

import numpy as np

from cfrace.rehearsal.loop_timing import GOALS_MS, bench_loop

FIGURES = [("compute p50", lambda l: l["compute_ms"]["p50"]),
           ("compute p99", lambda l: l["compute_ms"]["p99"]),
           ("compute CPU p99", lambda l: l["compute_cpu_ms"]["p99"]),
           ("inference p50", lambda l: max(v["p50"] for v in l["inference_ms"].values())),
           ("inference p99", lambda l: l["inference_p99_ms"]),
           ("late p99", lambda l: l["late_ms"]["p99"]),
           ("jitter p99", lambda l: l["period_jitter_p99_ms"]),
           ("warm-up CPU / tick p50", lambda l: l["prewarm_ms"]["p50"] or 0.0),
           ("warm-up passes / tick", lambda l: l.get("prewarm_calls_mean") or 0.0)]

KEYS = {"prewarm_ms": float, "loop_cpu": str, "rt_priority": str}
DEFAULT_CONFIGS = "unpinned:loop_cpu=off,rt_priority=0;pinned:loop_cpu=auto,rt_priority=0;default:loop_cpu=auto,rt_priority=auto"


def parse_configs(text: str) -> dict[str, dict]:
    """'name:key=v,key=v;name2:...' -> {name: bench_loop keyword arguments}."""
    out = {}
    for part in filter(None, (p.strip() for p in text.split(";"))):
        name, _, rest = part.partition(":")
        kw = {}
        for item in filter(None, (x.strip() for x in rest.split(","))):
            key, _, value = item.partition("=")
            if key not in KEYS:
                raise SystemExit(f"--configs: unknown key {key!r} in {part!r} (known: {', '.join(KEYS)})")
            kw[key] = KEYS[key](value)
        if "prewarm_ms" in kw:
            kw["prewarm_s"] = kw.pop("prewarm_ms") / 1e3
        out[name] = kw
    return out


def run(configs: dict[str, dict], rounds: int, seconds: float, policies: str, json_path: str | None) -> dict:
    runs: dict[str, list[dict]] = {name: [] for name in configs}
    t0 = time.strftime("%Y-%m-%d %H:%M:%S")
    for r in range(rounds):
        for name, kw in configs.items():
            res = bench_loop(seconds, policies=policies, **kw)
            runs[name].append(res)
            loop = res["loop"]
            print(f"round {r + 1} {name}: compute {loop['compute_ms']['p50']:.3f} / {loop['compute_ms']['p99']:.3f}, "
                  f"inference p99 {loop['inference_p99_ms']:.3f}, jitter p99 {loop['period_jitter_p99_ms']:.3f} ms "
                  f"(loop CPU {res['loop_cpu']}, FIFO {res['rt_fifo']}, load {res['load_avg'][0]:.2f})", flush=True)
    names = list(configs)
    print(f"\n{policies} actors, {rounds} rounds of {seconds:g} s per setting, {t0} .. {time.strftime('%H:%M:%S')}, "
          f"{os.cpu_count()} CPUs; medians over rounds, ms, ratio to '{names[0]}'")
    base = {fig: float(np.median([f(x["loop"]) for x in runs[names[0]]])) for fig, f in FIGURES}
    print(f"{'setting':>12s} " + " ".join(f"{fig:>22s}" for fig, _ in FIGURES) + "   goals met (compute, jitter, inference)")
    table = {}
    for name in names:
        cells, row = [], {}
        for fig, f in FIGURES:
            vals = [f(x["loop"]) for x in runs[name]]
            med = float(np.median(vals))
            row[fig] = {"median": med, "min": float(min(vals)), "max": float(max(vals))}
            ratio = f" x{med / base[fig]:.2f}" if base[fig] and name != names[0] and "warm" not in fig else ""
            spread = f" ({min(vals):.2f}..{max(vals):.2f})" if "p99" in fig else ""
            cells.append(f"{med:.3f}{spread}{ratio}".rjust(22))
        met = [sum(bool(x["goals_met"][k]) for x in runs[name]) for k in GOALS_MS]
        row["goals_met_rounds"] = dict(zip(GOALS_MS, met))
        table[name] = row
        n = len(runs[name])
        print(f"{name:>12s} " + " ".join(cells) + f"   {met[0]}/{n}, {met[1]}/{n}, {met[2]}/{n}")
    out = {"policies": policies, "rounds": rounds, "seconds": seconds, "start": t0,
           "configs": {k: {kk: str(vv) for kk, vv in v.items()} for k, v in configs.items()},
           "table_ms": table, "goals_ms": GOALS_MS,
           "runs": {k: [{"loop": x["loop"], "loop_cpu": x["loop_cpu"], "rt_fifo": x["rt_fifo"],
                         "load_avg": x["load_avg"], "time": x["time"]} for x in v] for k, v in runs.items()}}
    if json_path:
        with open(json_path, "w") as fh:
            json.dump(out, fh, indent=1, default=str)
    return out


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--configs", default=DEFAULT_CONFIGS, help="NAME:KEY=V,...;NAME:... (first = the reference)")
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--policies", default="paper", choices=["paper", "shipped"])
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    run(parse_configs(args.configs), args.rounds, args.seconds, args.policies, args.json)


if __name__ == "__main__":
    main()
