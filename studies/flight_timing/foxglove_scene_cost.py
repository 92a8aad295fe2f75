"""What building the Foxglove scene costs per flight-log record (cfrace.flight.log.foxglove_scene):
the /estimate (poses, 10-Hz drones and trails) and /setpoint (commands) records of a two-drone
race, CPU time per call, p50 / p99 over 3000 ticks. Prints one line per record kind.

    python studies/flight_timing/foxglove_scene_cost.py
"""

from __future__ import annotations

import time

import numpy as np

from cfrace.flight.log.foxglove_scene import FoxgloveScene
from cfrace.flight.safety.check import Fence
from cfrace.track import load_track


def main(ticks: int = 3000) -> None:
    track = load_track("lemniscate")
    scene = FoxgloveScene(track, Fence.from_track(track, 0.3), ["cf1", "cf2"], obstacles=False)
    for topic in ("/estimate", "/setpoint"):
        cost = []
        for k in range(ticks):
            pos = np.array([np.cos(k / 100), 5 + np.sin(k / 50), 1.0])
            msg = ({b: {"pos": pos + i, "vel": np.zeros(3), "quat": np.array([1.0, 0, 0, 0]), "age_s": 0.0,
                        "valid": True} for i, b in enumerate(("cf1", "cf2"))} if topic == "/estimate" else
                   {b: {"stopped": False, "thrust_n": 0.3, "thrust_counts": 30000, "rates_dps": np.array([10.0, -5, 2])}
                    for b in ("cf1", "cf2")})
            t0 = time.thread_time()
            scene.messages(topic, k * 0.01, msg, time.time_ns())
            cost.append(time.thread_time() - t0)
        us = np.array(cost) * 1e6
        print(f"{topic}: {np.percentile(us, 50):.0f} us p50, {np.percentile(us, 99):.0f} us p99 CPU per record "
              f"({ticks} ticks, two drones)")


if __name__ == "__main__":
    main()
