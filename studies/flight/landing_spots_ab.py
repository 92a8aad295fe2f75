"""The landing-spot choice of another revision against this checkout's: the same spots, and its CPU time.

    .venv/bin/python studies/flight/landing_spots_ab.py [OLD_REV] [--tracks lemniscate,complex] [--drones 3,8] [--cases 20]

OLD_REV's cfrace/flight/spots.py (git show; it imports only numpy and the standard library) is loaded
beside cfrace.flight.landing.spots. For each track and drone count, ``--cases`` random sets of stop points in the
arena land one drone after the other as the flight loop's tick does (choose_landing_spots with the
spots and paths chosen so far). Prints whether every spot agrees, and per tick (all drones) and per
single choice the median and worst CPU time (time.thread_time) of each version.
"""

from __future__ import annotations

import argparse
import importlib.util
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[2]


def load_revision(rev: str):
    """cfrace/flight/spots.py of ``rev`` as a module of its own."""
    text = subprocess.run(["git", "-C", str(REPO), "show", f"{rev}:cfrace/flight/spots.py"], check=True,
                          capture_output=True, text=True).stdout
    path = Path(tempfile.mkdtemp()) / "spots_old.py"
    path.write_text(text)
    spec = importlib.util.spec_from_file_location("spots_old", path)
    mod = importlib.util.module_from_spec(spec)
    sys.modules["spots_old"] = mod   # dataclasses look their module up
    spec.loader.exec_module(mod)
    return mod


def land_one_by_one(mod, track, stops) -> tuple[np.ndarray | None, list[float]]:
    """The spots (None: no free spot for some drone) and each choice's CPU time (s)."""
    cfg, paths, others, took = mod.LandingConfig(), [], [], []
    mod.candidate_spots(track, cfg)          # as LandingSetup.for_race does before the race
    for stop in stops:
        t0 = time.thread_time()
        try:
            spot = mod.choose_landing_spots(track, [stop], others, cfg, paths)[0]
        except ValueError:
            return None, took
        took.append(time.thread_time() - t0)
        paths.append((stop, spot))
        others.append(spot)
    return np.array(others), took


def compare(old, new, track_name: str, drones: int, cases: int, seed: int = 0) -> dict:
    from cfrace.track import load_track

    track, rng = load_track(track_name), np.random.default_rng(seed)
    a, same, ticks, single = track.arena, True, {"old": [], "new": []}, {"old": [], "new": []}
    for _ in range(cases):
        stops = np.column_stack([rng.uniform(a.x[0] + 0.1, a.x[1] - 0.1, drones),
                                 rng.uniform(a.y[0] + 0.1, a.y[1] - 0.1, drones)])
        spots = {}
        for name, mod in (("old", old), ("new", new)):
            spots[name], took = land_one_by_one(mod, track, stops)
            ticks[name].append(sum(took))
            single[name] += took
        same &= (spots["old"] is None) == (spots["new"] is None) and (
            spots["old"] is None or np.array_equal(spots["old"], spots["new"]))
    ms = {f"{k} {v} {fname}": round(1e3 * float(f(d[v])), 2) for k, d in (("tick", ticks), ("choice", single))
          for v in ("old", "new") for f, fname in ((np.median, "median"), (np.max, "max")) if d[v]}
    return {"track": track_name, "drones": drones, "cases": cases, "same_spots": bool(same), "ms": ms}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("old_rev", nargs="?", default="b1493e9")
    ap.add_argument("--tracks", default="lemniscate,complex")
    ap.add_argument("--drones", default="3,8")
    ap.add_argument("--cases", type=int, default=20)
    args = ap.parse_args()
    import cfrace.flight.landing.spots as new

    old = load_revision(args.old_rev)
    for track in args.tracks.split(","):
        for n in (int(x) for x in args.drones.split(",")):
            r = compare(old, new, track, n, args.cases)
            ms = r["ms"]
            print(f"{track}, {n} drones, {args.cases} cases: same spots {r['same_spots']}; CPU ms per tick median "
                  f"{ms['tick old median']} -> {ms['tick new median']}, worst {ms['tick old max']} -> "
                  f"{ms['tick new max']}; per choice worst {ms['choice old max']} -> {ms['choice new max']}")


if __name__ == "__main__":
    main()
