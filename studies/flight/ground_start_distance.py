"""From how far before gate 0 do the shipped policies take off from the floor?

For each distance D: the track's YAML with `spawn.ground_distance: D` (a temporary copy), a
lockstep dry-run of ours vs ds (the policies' training profile), 4 s; prints the gates each drone
passed and how it ended. Usage:

    .venv/bin/python studies/flight/ground_start_distance.py [--track lemniscate] [--distances 0.6,0.8,1.0,1.2,1.4]
"""

from __future__ import annotations

import argparse
import re
import tempfile
from pathlib import Path

from cfrace.flight.config import FlightConfig
from cfrace.rehearsal.dryrun import dry_run
from cfrace.paths import POLICIES_DIR, TRACKS_DIR


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--track", default="lemniscate")
    ap.add_argument("--distances", default="0.6,0.8,1.0,1.2,1.4")
    args = ap.parse_args()
    src = (TRACKS_DIR / f"{args.track}.yaml").read_text()
    with tempfile.TemporaryDirectory() as tmp:
        for d in (float(x) for x in args.distances.split(",")):
            path = Path(tmp) / f"{args.track}_gd{d:g}.yaml"
            path.write_text(re.sub(r"ground_distance: [0-9.]+", f"ground_distance: {d}", src))
            cfg = FlightConfig(track=str(path), ego=str(POLICIES_DIR / f"ours_{args.track}.onnx"),
                               opp=str(POLICIES_DIR / f"ds_{args.track}.onnx"), profile="cf2x_paper",
                               quiet=True, timeout_s=4.0, log=None)
            res = dry_run(cfg, lockstep=True).to_json()
            print(f"{d:.1f} m: " + ", ".join(f"{x['name']} {x['gates_passed']} gates ({x['stop_kind']})"
                                            for x in res["drones"]), flush=True)


if __name__ == "__main__":
    main()
