"""Print the markdown table of docs/benchmarks.md from `cfrace bench sim --json` files.

    python benchmarks/sim_table.py benchmarks/results/sim_threads1.json [more.json ...]

Rates are drone-steps per second (one drone, one 2 ms physics step), the fastest of the repeats;
the median is in brackets when it differs by more than 10 %. On a shared machine the last columns
divide each side's best rate by the CPU share it got during that repeat (process CPU time / wall
time): drone-steps per CPU-second, a steadier figure when other work competes for the cores.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

MODES = ("c", "eager", "compiled")


def rate(x: float | None, median: float | None = None) -> str:
    if x is None:
        return "-"
    text = f"{x / 1e6:.2f} M" if x >= 1e5 else f"{x / 1e3:.1f} k"
    if median is not None and abs(median - x) > 0.1 * x:
        text += f" ({median / 1e6:.2f} M)" if median >= 1e5 else f" ({median / 1e3:.1f} k)"
    return text


def table(doc: dict) -> str:
    results, peer = doc["results"], doc.get("peer", [])
    modes = [m for m in MODES if any(r["mode"] == m for r in results)]
    head = ["worlds", "drones", *[f"cfrace {m}" for m in modes], "crazyflow", "best cfrace / crazyflow",
            "per CPU-s: cfrace best / crazyflow"]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    for w, d in dict.fromkeys((r["worlds"], r["drones"]) for r in results):
        rs = {r["mode"]: r for r in results if (r["worlds"], r["drones"]) == (w, d)}
        cf = next((p for p in peer if p["total_drones"] == w * d), None)
        top = max(rs.values(), key=lambda r: r["drone_steps_per_s"])
        best = top["drone_steps_per_s"]
        cells = [str(w), f"{d} x {w} = {w * d}"]
        cells += [rate(rs[m]["drone_steps_per_s"], rs[m].get("median_drone_steps_per_s")) if m in rs else "-"
                  for m in modes]
        cells.append(rate(cf["drone_steps_per_s"], cf.get("median_drone_steps_per_s")) if cf else "-")
        cells.append(f"{best / cf['drone_steps_per_s']:.2f}x" if cf else "-")
        if cf and top.get("cpu_per_wall") and cf.get("cpu_per_wall"):
            a, b = best / top["cpu_per_wall"], cf["drone_steps_per_s"] / cf["cpu_per_wall"]
            cells.append(f"{rate(a)} / {rate(b)} = {a / b:.2f}x")
        else:
            cells.append("-")
        lines.append("| " + " | ".join(cells) + " |")
    m = doc["machine"]
    lines.append("")
    lines.append(f"{m['cpu']}, {m['cores']} cores, torch {m['torch']} with {m['torch_threads']} thread(s), "
                 f"{m['date']}, load average {m['loadavg_start'][0]:.1f} at start, "
                 f"{m.get('loadavg_end', [float('nan')])[0]:.1f} at end.")
    return "\n".join(lines)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("files", nargs="+", help="`cfrace bench sim --json` files")
    for path in ap.parse_args().files:
        try:
            doc = json.loads(Path(path).read_text())
            text = table(doc)
        except (OSError, ValueError, KeyError, TypeError) as e:
            print(f"sim_table: {path}: not a readable `cfrace bench sim --json` file ({type(e).__name__}: {e})",
                  file=sys.stderr)
            return 2
        print(f"<!-- {path} -->")
        print(text)
        print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
