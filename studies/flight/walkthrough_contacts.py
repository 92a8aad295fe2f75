"""Drone-drone contacts of one pair of policies through the three ways the stack races it: the
lockstep dry-run, the real-time dry-run, and `cfrace fly` against `cfrace sim serve` (two processes,
as in docs/walkthrough.md).

    python studies/flight/walkthrough_contacts.py [--runs 10] [--paths lockstep,realtime,serve]
        [--track lemniscate] [--ego ours] [--opp ds] [--laps 1] [--extra "--profile cf2x_paper"]
        [--json FILE] [--keep DIR]

Run k uses seed k (`--seed` of the dry-run and of `sim serve`). Each run's flight log gives the
distance between the two drones at every tick of the race (the mocap poses the loop read);
a contact is a tick where it is below the simulator's drone-drone contact distance, 2 x (the
profile's collision_radius + cfrace.sim.collisions.CONTACT_MARGIN): the simulator pushes touching
drones apart to two radii, so a touch shows as a distance of two radii, not less. Per path: the runs with a contact, the
first contact's time, the closest approach, how the races ended.
"""

from __future__ import annotations

import argparse
import json
import os
import shlex
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from cfrace.rehearsal.loop_timing import _free_base_port

BIN = Path(sys.executable).parent / "cfrace"


def contacts(log_path: Path, bodies=("cf1", "cf2")) -> dict:
    """From a flight log: the closest approach of the two bodies during the race (before the first
    landing began) and the ticks closer than the two collision radii."""
    from cfrace.drone import load_profile
    from cfrace.flight.log.writer import read_log
    from cfrace.sim.collisions import CONTACT_MARGIN

    log = read_log(log_path)
    radius = load_profile(log.meta["profile"]).collision_radius
    t_land = min((m["t_start"] for _, m in log.messages("/landing") if m.get("t_start") is not None),
                 default=np.inf)
    ts, ds = [], []
    for t, m in log.messages("/mocap/pose"):
        p = m["poses"]
        if t >= t_land or not all(b in p for b in bodies):
            continue
        ts.append(t)
        ds.append(float(np.linalg.norm(np.subtract(p[bodies[0]]["pos"], p[bodies[1]]["pos"]))))
    ts, ds = np.array(ts), np.array(ds)
    hit = ds < 2.0 * (radius + CONTACT_MARGIN)
    k = int(np.argmin(ds)) if len(ds) else 0
    return {"contact": bool(hit.any()), "t_contact": float(ts[hit][0]) if hit.any() else None,
            "contact_ticks": int(hit.sum()), "d_min_m": round(float(ds[k]), 4) if len(ds) else None,
            "t_d_min": round(float(ts[k]), 2) if len(ds) else None, "radius_m": radius}


def _run(cmd: list[str], cwd: Path, timeout: float = 180.0) -> int:
    env = dict(os.environ, OMP_NUM_THREADS="1", COLUMNS="160")
    return subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=timeout).returncode


def race(path: str, k: int, a, work: Path) -> dict:
    """One race of ``path`` with seed k; its exit code, result and contacts."""
    log, js = work / f"{path}_{k}.mcap", work / f"{path}_{k}.json"
    common = ["--track", a.track, "--ego", a.ego, "--opp", a.opp, "--laps", str(a.laps), "--log", str(log),
              "--json", str(js), *shlex.split(a.extra)]
    if path in ("lockstep", "realtime"):
        code = _run([str(BIN), "sim", "dry-run", *common, "--seed", str(k), "--quiet",
                     *(["--lockstep"] if path == "lockstep" else [])], work)
    else:
        base = _free_base_port(2)
        serve = subprocess.Popen([str(BIN), "sim", "serve", "--track", a.track, "--port", str(base), "--seed", str(k),
                                  *shlex.split(a.serve_extra)], cwd=work, stdout=subprocess.PIPE,
                                 stderr=subprocess.STDOUT, text=True, env=dict(os.environ, OMP_NUM_THREADS="1"))
        try:
            seen = ""
            while "Ctrl-C" not in seen:
                line = serve.stdout.readline()
                if not line:
                    raise RuntimeError(f"sim serve ended: {seen}")
                seen += line
            code = _run([str(BIN), "fly", *common, "--uris", f"udp://127.0.0.1:{base},udp://127.0.0.1:{base + 1}",
                         "--mocap", f"sim://127.0.0.1:{base - 1}", "--quiet"], work)
        finally:
            serve.terminate()
            serve.communicate(timeout=30)
    r = json.loads(js.read_text()) if js.exists() else {}
    row = {"path": path, "seed": k, "exit": code, "end": r.get("end"), "winner": r.get("winner"),
           "safety": sorted({e["kind"] for e in r.get("safety_events", [])}),
           "crashed": [d.get("crashed") for d in r.get("drones_final") or []]}
    if log.exists():
        row |= contacts(log)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", type=int, default=10)
    ap.add_argument("--paths", default="lockstep,realtime,serve")
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--ego", default="ours")
    ap.add_argument("--opp", default="ds")
    ap.add_argument("--laps", type=int, default=1)
    ap.add_argument("--extra", default="", help="more options of `fly` and `sim dry-run`")
    ap.add_argument("--serve-extra", default="", help="more options of `sim serve`")
    ap.add_argument("--json", default=None)
    ap.add_argument("--keep", default=None, help="keep the logs and results in this folder")
    a = ap.parse_args()
    work = Path(a.keep) if a.keep else Path(tempfile.mkdtemp(prefix="contacts-"))
    work.mkdir(parents=True, exist_ok=True)
    rows, t0 = [], time.monotonic()
    for path in a.paths.split(","):
        for k in range(a.runs):
            row = race(path, k, a, work)
            rows.append(row)
            print(f"{path:8s} seed {k:2d}: exit {row['exit']} end {row['end']} contact {row.get('contact')} "
                  f"at {row.get('t_contact')} s, closest {row.get('d_min_m')} m at {row.get('t_d_min')} s, "
                  f"safety {','.join(row['safety']) or '-'}", flush=True)
    summary = {}
    for path in a.paths.split(","):
        mine = [r for r in rows if r["path"] == path]
        hits = [r for r in mine if r.get("contact")]
        summary[path] = {"runs": len(mine), "contacts": len(hits), "t_contact": [r["t_contact"] for r in hits],
                         "exit0": sum(r["exit"] == 0 for r in mine),
                         "d_min_m": [r.get("d_min_m") for r in mine]}
        when = ", ".join(f"{r['t_contact']:.2f}" for r in hits) or "-"
        print(f"{path}: {len(hits)} of {len(mine)} runs with a drone-drone contact (at {when} s); "
              f"exit 0 in {summary[path]['exit0']}", flush=True)
    print(f"load average at the end {os.getloadavg()[0]:.2f}; {time.monotonic() - t0:.0f} s")
    if a.json:
        Path(a.json).write_text(json.dumps({"args": vars(a), "summary": summary, "rows": rows,
                                            "load_end": os.getloadavg()[0]}, indent=1) + "\n")


if __name__ == "__main__":
    main()
