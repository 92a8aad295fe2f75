"""How far a drone whose link is lost flies, without and with `fly --estop-watchdog`.

For each cut time T: `cfrace fly` (shipped ours vs ds, lemniscate) against simulated Crazyflies
served in this process; drone 0's link goes through a UDP relay that drops everything from race
time T on. The drone's ground truth is sampled until it lies still: its highest point and how far
from the cut it comes to rest, and when its motors went off (the firmware's watchdog). Usage:

    .venv/bin/python studies/flight/link_loss_watchdog.py --cuts 3,4,5 [--json FILE]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time

import numpy as np

from cfrace.rehearsal.faults import UdpCutRelay
from cfrace.simcf.firmware import SimFleet
from cfrace.simcf.server import SimCrazyflieServer

CLI = [sys.executable, "-c", "from cfrace.cli.main import main; main()"]


def one(cut_s: float, watchdog: bool, profile: str = "cf2x_paper") -> dict:
    fleet = SimFleet("lemniscate", profile, 2, obstacles=False)
    with SimCrazyflieServer(fleet, base_port=0) as server:
        relay = UdpCutRelay(server.ports[0])
        uris = f"{relay.uri},udp://127.0.0.1:{server.ports[1]}"
        fly = subprocess.Popen(CLI + ["fly", "--track", "lemniscate", "--ego", "ours", "--opp", "ds", "--uris", uris,
                                      "--mocap", f"sim://127.0.0.1:{server.pose_port}", "--profile", profile,
                                      "--quiet", "--timeout-s", "10", "--log", "/dev/null"]
                               + (["--estop-watchdog"] if watchdog else []),
                               stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        while fleet.status(0)["setpoints_received"] == 0 and fly.poll() is None:   # the race starts
            time.sleep(0.01)
        t_start = fleet.time
        while fleet.time < t_start + cut_s:
            time.sleep(0.005)
        relay.cut()
        t_cut, path, off_at = fleet.time, [fleet.state(0)["pos"]], None
        while fleet.time < t_cut + 8.0:
            time.sleep(0.02)
            st = fleet.status(0)
            if off_at is None and (st["emergency_stopped"] or st["watchdog"] == "shutdown"):
                off_at = fleet.time - t_cut
            path.append(fleet.state(0)["pos"])
            if off_at is not None and np.linalg.norm(fleet.state(0)["vel"]) < 1e-3:
                break
        fly.wait(30)
        relay.close()
    p = np.array(path)
    return {"cut_s": cut_s, "estop_watchdog": watchdog, "motors_off_after_s": off_at,
            "max_z_m": float(p[:, 2].max()),
            "rest_from_cut_m": float(np.linalg.norm(p[-1] - p[0])),
            "path_m": float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())}


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--cuts", default="3,4,5", help="race times (s) of the cut, comma-separated")
    ap.add_argument("--json", default=None)
    args = ap.parse_args()
    rows = []
    for cut in (float(c) for c in args.cuts.split(",")):
        for wd in (False, True):
            r = one(cut, wd)
            rows.append(r)
            print(f"cut {cut:4.1f} s  estop_watchdog {str(wd):5}  motors off after {r['motors_off_after_s']:.2f} s  "
                  f"max z {r['max_z_m']:5.1f} m  at rest {r['rest_from_cut_m']:5.1f} m from the cut  "
                  f"path {r['path_m']:5.1f} m", flush=True)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)


if __name__ == "__main__":
    main()
