"""Do the landings at a race's end keep clear of the gates? Lockstep races ended by the timeout at
every moment of a window, each ending with both drones landing from wherever they were.

    .venv/bin/python studies/flight/race_end_landings.py [--ego ds] [--opp ours] [--profile cf2x_paper]
        [--from 1.0] [--to 9.0] [--step 0.03] [--json FILE]
    .venv/bin/python studies/flight/race_end_landings.py --policies ours,ds,ours,ds,ours,ds,ours,ds --track complex ...
        (a swarm: drones that crashed racing are not landings; each race end's slowest tick in CPU ms)
    .venv/bin/python studies/flight/race_end_landings.py --compare NEW.json:OLD.json ... [--json F]
        (the same scan by two code versions: bad race ends, landings that start at another time)

Per race end: whether a simulated drone crashed (the simulator's crash flag at the end: a gate frame,
an obstacle, a floor impact), the safety events that acted and the pose outliers (a crash in the
air drops the simulated drone to the floor in one step, which the flight loop sees as outliers).
Prints the race ends with a crash or an event and a summary line; the JSON holds every race end.
A race end whose safety events all happen, at the same ticks, in the same race not ended in the window
(the reference race), and whose crashed drones all crash in that race too, is marked "as in the
race": drones flying on through the gate ahead on their policies (softsafe.FLY_THROUGH_MAX_S)
crashed at the tick at which they crash racing.
A race end is a landing from one place and speed: the window samples the places of a lap and more
(the races run 3 laps; the timeout ends them before).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from cfrace.flight.config import FlightConfig
from cfrace.rehearsal.dryrun import dry_run


def race_end(ego: str, opp: str, profile: str, t_end: float, track: str = "lemniscate", policies: tuple = ()) -> dict:
    cfg = FlightConfig(track=track, ego=ego, opp=opp, policies=policies, profile=profile, laps=3, quiet=True,
                       timeout_s=t_end)
    r = dry_run(cfg, lockstep=True).to_json()
    landing = {d["body"] for d in r["drones"] if d["landing"] is not None}   # others crashed racing (a swarm)
    return {"t_end": t_end, "end": r["end"], "max_tick_cpu_ms": r["loop"]["compute_cpu_ms"]["max"],
            "crashed": [f["body"] for f in r["drones_final"] if f["crashed"] and (not policies or f["body"] in landing)],
            "acted": [(e["t"], e["kind"], e["drone"]) for e in r["safety_events"] if e["action"] != "none"
                      and (not policies or e["t"] >= t_end)],
            "all_acted": [(e["t"], e["kind"], e["drone"]) for e in r["safety_events"] if e["action"] != "none"],
            "all_crashed": [f["body"] for f in r["drones_final"] if f["crashed"]],
            "outliers": sum(e["kind"] == "pose_outlier" for e in r["safety_events"]),
            "landings": {d["name"]: (d["stop_kind"], (d["landing"] or {}).get("t_start")) for d in r["drones"]}}


def as_in_race(row: dict, reference: dict) -> bool:
    """Do all of row's safety events happen in the reference race at the same ticks, and do its
    crashed drones crash there too?"""
    ref = {(round(t, 2), kind, drone) for t, kind, drone in reference["all_acted"]}
    return bool(row["acted"]) and all((round(t, 2), kind, drone) in ref for t, kind, drone in row["acted"]) \
        and set(row["crashed"]) <= set(reference["all_crashed"])


def compare(pairs: list[str], out: str = "") -> None:
    """NEW.json:OLD.json pairs of the same scan by two code versions: bad race ends of each, and the
    landings that start at another time (or end another way) in the new one, with the shift."""
    doc = {}
    for pair in pairs:
        new_path, old_path = pair.split(":")
        new, old = (json.load(open(x)) for x in (new_path, old_path))
        shifts, other = [], 0
        for rn, ro in zip(new["rows"], old["rows"]):
            for drone, (kind, t) in rn["landings"].items():
                kind_old, t_old = ro["landings"].get(drone, (None, None))
                if (kind, t) != (kind_old, t_old):
                    if kind == kind_old and t is not None and t_old is not None:
                        shifts.append(round(t - t_old, 3))
                    else:
                        other += 1
        row = {"bad": [new["bad"], old["bad"]], "as_in_race": [new["as_in_race"], old["as_in_race"]],
               "runs": new["runs"], "landings_shifted": len(shifts), "landings_changed_otherwise": other,
               "shift_s": [min(shifts), max(shifts)] if shifts else None}
        doc[Path(new_path).name] = row
        print(f"{new_path}: bad {row['bad'][0]} (old {row['bad'][1]}) of {row['runs']}; {len(shifts)} landings "
              f"start at another time ({row['shift_s']} s), {other} otherwise changed")
    if out:
        Path(out).write_text(json.dumps(doc, indent=1))


def main() -> None:
    if sys.argv[1:2] == ["--compare"]:
        ap = argparse.ArgumentParser(description=compare.__doc__.splitlines()[0])
        ap.add_argument("--compare", nargs="+", metavar="NEW.json:OLD.json", required=True)
        ap.add_argument("--json", default="")
        a = ap.parse_args()
        compare(a.compare, a.json)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--ego", default="ds")
    ap.add_argument("--opp", default="ours")
    ap.add_argument("--profile", default="cf2x_paper")
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--policies", default="", help="P1,...,PN: an N-drone field instead of --ego/--opp")
    ap.add_argument("--from", dest="t0", type=float, default=1.0)
    ap.add_argument("--to", dest="t1", type=float, default=9.0)
    ap.add_argument("--step", type=float, default=0.03)
    ap.add_argument("--json", default="")
    a = ap.parse_args()
    policies = tuple(p for p in a.policies.split(",") if p)
    reference = race_end(a.ego, a.opp, a.profile, a.t1 + 2.0, a.track, policies)
    rows = []
    for t_end in np.round(np.arange(a.t0, a.t1 + 1e-9, a.step), 3):
        row = race_end(a.ego, a.opp, a.profile, float(t_end), a.track, policies)
        row["as_in_race"] = as_in_race(row, reference)
        rows.append(row)
        if row["crashed"] or row["acted"] or row["outliers"]:
            print(f"{row['t_end']:.2f} s: crashed {row['crashed']}, acted {row['acted']}, outliers {row['outliers']}"
                  + (" (as in the race)" if row["as_in_race"] else ""), flush=True)
    bad = [r for r in rows if r["crashed"] or r["acted"]]
    racing = sum(r["as_in_race"] for r in bad)
    who = a.policies or f"{a.ego} vs {a.opp}"
    ticks = [r["max_tick_cpu_ms"] for r in rows]
    print(f"{who} on {a.track}, {a.profile}: {len(bad)} of {len(rows)} race ends ({a.t0:g}-{a.t1:g} s every "
          f"{a.step:g} s) crashed a drone or stopped one, {racing} of them as in the race; slowest tick {np.median(ticks):.1f} ms CPU median, "
          f"{max(ticks):.1f} ms worst")
    if a.json:
        doc = {"ego": a.ego, "opp": a.opp, "policies": a.policies, "track": a.track, "profile": a.profile, "from": a.t0, "to": a.t1, "step": a.step,
               "bad": len(bad), "as_in_race": racing, "runs": len(rows), "rows": rows}
        with open(a.json, "w") as f:
            json.dump(doc, f, indent=1)


if __name__ == "__main__":
    main()
