"""`cfrace bench loop` of two commits side by side, interleaved, in one run (ratios new / old).

    python benchmarks/loop_commits_ab.py OLD_REV [--rounds 2] [--seconds 8] [--prewarm-ms 0,3]
                                         [--policies paper|shipped] [--json FILE]

OLD_REV's tree is taken with `git archive` into a temporary directory; the new side is this
checkout. Each round runs every (commit, warm-up window) once, in turn (the commits' order turned
every round), with the same interpreter;
the table gives each arm's median over the rounds of the p99 figures and the ratio against the old
commit with the same window. The machine is shared: say what else ran.
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
FIGURES = ("compute_p99_ms", "period_jitter_p99_ms", "inference_p99_ms")


def tree(rev: str, into: Path) -> Path:
    """The files of ``rev`` under ``into`` (git archive)."""
    tar = into / "tree.tar"
    subprocess.run(["git", "-C", str(REPO), "archive", "-o", str(tar), rev], check=True)
    with tarfile.open(tar) as t:
        t.extractall(into / "src", filter="data")
    return into / "src"


def bench(src: Path, prewarm_ms: float, seconds: float, policies: str, out: Path) -> dict:
    code = f"import sys; sys.path.insert(0, {str(src)!r}); from cfrace.cli.main import main; main()"
    subprocess.run([sys.executable, "-c", code, "bench", "loop", "--duration-s", str(seconds), "--floor-s", "0",
                    "--prewarm-ms", str(prewarm_ms), "--policies", policies, "--json", str(out)],
                   check=True, cwd=src, stdout=subprocess.DEVNULL)
    return json.loads(out.read_text())["loop"]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old_rev")
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--prewarm-ms", default="0,3")
    ap.add_argument("--policies", default="paper", choices=["paper", "shipped"])
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    windows = [float(x) for x in args.prewarm_ms.split(",")]
    with tempfile.TemporaryDirectory(prefix="cfrace-ab-") as tmp:
        sides = {"old": tree(args.old_rev, Path(tmp)), "new": REPO}
        runs: dict[tuple[str, float], list[dict]] = {}
        for r in range(args.rounds):
            for w in windows:
                for side in (("old", "new") if r % 2 == 0 else ("new", "old")):   # neither always second
                    src = sides[side]
                    loop = bench(src, w, args.seconds, args.policies, Path(tmp) / f"{side}{w}_{r}.json")
                    runs.setdefault((side, w), []).append(loop)
                    print(f"round {r} {side} prewarm {w:g} ms: " + ", ".join(f"{f} {loop[f]}" for f in FIGURES),
                          flush=True)
    rows = []
    for (side, w), loops in runs.items():
        med = {f: statistics.median(x[f] for x in loops) for f in FIGURES}
        old = {f: statistics.median(x[f] for x in runs[("old", w)]) for f in FIGURES}
        rows.append({"side": side, "prewarm_ms": w, **med, **{f"{f}_vs_old": round(med[f] / old[f], 3) for f in FIGURES}})
    print(f"{'side':5} {'prewarm':>8} " + " ".join(f"{f:>22}" for f in FIGURES))
    for row in rows:
        print(f"{row['side']:5} {row['prewarm_ms']:>6g}ms "
              + " ".join(f"{row[f]:>12.3f} ({row[f + '_vs_old']:.2f}x)" for f in FIGURES))
    if args.json:
        Path(args.json).write_text(json.dumps({"old_rev": args.old_rev, "rounds": args.rounds,
                                               "seconds": args.seconds, "rows": rows}, indent=1) + "\n")


if __name__ == "__main__":
    main()
