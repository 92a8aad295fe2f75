"""cflib's own example scripts, unmodified, against the simulated Crazyflies (`cfrace sim script`,
real cflib over UDP, real time): the ones under examples/autonomy and examples/step-by-step that need
only a Crazyflie and a positioning system. Each runs as `cfrace sim script` runs it, in a process of
its own, against drones served as `cfrace sim serve` serves them (cf21bl, no obstacles), placed where
the script expects them (docs/simcf.md, "cflib's examples"); each must exit 0 having flown what it
asks, and land.

The scripts come from a checkout of bitcraze/crazyflie-lib-python: CFRACE_CFLIB_EXAMPLES names its
examples folder (the one holding autonomy/ and step-by-step/). Without it, these tests skip.
"""

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("cflib")

from cfrace.errors import LinkError  # noqa: E402
from cfrace.simcf.firmware import SimFleet  # noqa: E402
from cfrace.simcf.server import SimCrazyflieServer  # noqa: E402

EXAMPLES = os.environ.get("CFRACE_CFLIB_EXAMPLES", "")
SQUARE = [(-0.5, 0.5), (0.5, 0.5), (0.5, -0.5), (-0.5, -0.5)]   #: sbs_swarm.py's layout, drones 0-3, 1 m apart

#: script: (drone start positions x, y; decks; highest point it flies to m or None; timeout s)
SCRIPTS = {
    "autonomy/autonomous_sequence.py": ([(0.0, 0.0)], ("lighthouse",), 1.2, 120),
    "autonomy/autonomous_sequence_high_level.py": ([(0.0, 0.0)], ("lighthouse",), 1.0, 90),
    "autonomy/motion_commander_demo.py": ([(0.0, 0.0)], ("lighthouse",), 0.8, 90),
    "step-by-step/sbs_connect_log_param.py": ([(0.0, 0.0)], ("lighthouse",), None, 60),
    "step-by-step/sbs_motion_commander.py": ([(0.0, 0.0)], ("lighthouse", "flow"), 0.5, 60),
    "step-by-step/sbs_swarm.py": (SQUARE, ("lighthouse",), 1.0, 120),
}


def serve(starts, decks):
    """The fleet `cfrace sim serve` would serve (cf21bl, no obstacles) at these x, y on the floor, on
    consecutive free ports: (fleet, started server)."""
    fleet = SimFleet("lemniscate", "cf21bl", len(starts), arming_required=True, obstacles=False, decks=decks,
                     start_positions=[(x, y, 0.0) for x, y in starts])
    floor = fleet.state(0)["pos"][2]
    assert floor >= 0.0
    for base in range(23000 + (os.getpid() % 500) * 20, 40000, 97):
        server = SimCrazyflieServer(fleet, base_port=base)
        try:
            server.start()
        except LinkError:
            continue
        return fleet, server
    pytest.fail("no free UDP ports for the simulated drones")


def heights(fleet, stop):
    """Each drone's highest and last height (m), polled every 20 ms until stop is set."""
    top = np.zeros(fleet.n)
    rows = {"top": top, "last": top}
    while not stop.is_set():
        _, poses = fleet.poses()
        z = np.array([poses[name][0][2] for name in fleet.body_names])
        rows["top"] = np.maximum(rows["top"], z)
        rows["last"] = z
        time.sleep(0.02)
    return rows


@pytest.mark.parametrize("script", sorted(SCRIPTS))
def test_cflib_example_runs_unmodified_and_flies(script, tmp_path):
    if not EXAMPLES:
        pytest.skip("CFRACE_CFLIB_EXAMPLES is not set (the examples folder of a crazyflie-lib-python checkout)")
    path = Path(EXAMPLES) / script
    if not path.is_file():
        pytest.skip(f"{path}: not in the cflib checkout CFRACE_CFLIB_EXAMPLES names")
    starts, decks, height, timeout = SCRIPTS[script]
    fleet, server = serve(starts, decks)
    stop, out = threading.Event(), {}
    watcher = threading.Thread(target=lambda: out.update(heights(fleet, stop)), daemon=True)
    watcher.start()
    try:
        run = subprocess.run([sys.executable, "-m", "cfrace", "sim", "script", str(path), "--port",
                              str(server.ports[0]), "--drones", str(fleet.n)], cwd=tmp_path, capture_output=True,
                             text=True, timeout=timeout)
        time.sleep(0.5)
    finally:
        stop.set()
        watcher.join()
        server.stop()
    assert run.returncode == 0, run.stdout[-2000:] + run.stderr[-2000:]
    status = [fleet.status(i) for i in range(fleet.n)]
    assert not any(s["crashed"] for s in status), status
    # cflib's close_link sends one zero setpoint and goes silent: a drone whose motors ran less than
    # 1.5 s before locks 2 s later (supervisor_state_machine.c, WarningLevelOut), as a real one does;
    # sbs_swarm.py closes its four links one after the other, up to 1 s each. Nothing else may stop one.
    assert all(s["emergency_reason"] in ("", "commander watchdog timeout in flight") for s in status), status
    if height is None:                                   # no flight: it read and wrote parameters
        assert "stabilizer.estimator set at number" in run.stdout, run.stdout
        assert out["top"].max() < 0.05
        return
    assert np.all(out["top"] > 0.8 * height) and np.all(out["top"] < height + 0.3), out["top"]
    assert np.all(out["last"] < 0.1), out["last"]        # landed


def test_radio_uris_reach_the_served_drones_and_a_missing_script_is_one_line():
    from cfrace.simcf.cflib_script import radio_address, served_links

    links = served_links(19850, 2)
    assert links[radio_address("radio://0/80/2M/E7E7E7E7E7")] == "udp://127.0.0.1:19850"   # the default: the first
    assert links[radio_address("radio://0/20/2M/E7E7E7E701?safelink=0")] == "udp://127.0.0.1:19850"
    assert links[radio_address("radio://0/20/2M/E7E7E7E702")] == "udp://127.0.0.1:19851"
    assert radio_address("radio://0/80/2M/E7E7E7E703") not in links                    # no third drone
    assert radio_address("radio://0/80") == radio_address("radio://0/80/2M/E7E7E7E7E7")
    assert radio_address("udp://127.0.0.1:19850") is None
    run = subprocess.run([sys.executable, "-m", "cfrace", "sim", "script", "no_such_script.py"],
                         capture_output=True, text=True, timeout=60)
    assert run.returncode == 2 and run.stderr.strip().count("\n") == 0 and "no_such_script.py" in run.stderr
    assert "Traceback" not in run.stderr
