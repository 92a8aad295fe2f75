"""docs/walkthrough.md, run step by step with its own commands: serve, dry-run, fly against the
served drones (with the live Foxglove server), open the log, plot. The default ports are swapped
for free ones (other tests or a running `sim serve` may hold them); nothing else is changed."""

from __future__ import annotations

import json
import os
import re
import shlex
import signal
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DOC = ROOT / "docs" / "walkthrough.md"
BIN = Path(sys.executable).parent


def blocks() -> list[list[str]]:
    """The bash blocks of the walkthrough, in order, as lists of lines."""
    return [[line for line in b.splitlines() if line.strip()]
            for b in re.findall(r"```bash\n(.*?)```", DOC.read_text(), re.S)]


def _free_ports(n: int, span: int = 3) -> list[int]:
    """n base ports, each with base-1 .. base+span-1 free (a `sim serve` uses base-1, base, base+1)."""
    out = []
    while len(out) < n:
        with socket.socket(socket.AF_INET, socket.SOCK_DGRAM) as s:
            s.bind(("127.0.0.1", 0))
            base = s.getsockname()[1]
        if not 1025 < base < 65000:
            continue
        try:
            socks = []
            for p in range(base - 1, base + span):
                for kind in (socket.SOCK_DGRAM, socket.SOCK_STREAM):
                    x = socket.socket(socket.AF_INET, kind)
                    x.bind(("127.0.0.1", p))
                    socks.append(x)
        except OSError:
            continue
        finally:
            for x in locals().get("socks", []):
                x.close()
        out.append(base)
    return out


def test_install_step_is_the_readme_install():
    install = blocks()[0][0]
    readme = (ROOT / "README.md").read_text()
    assert install + " && .venv/bin/cfrace sim dry-run" in readme
    assert '".[dev,stand,cluster,envs,examples,foxglove]"' in install
    ci = (ROOT / ".ci" / "run").read_text()
    assert '".[dev,stand,cluster,envs,examples,foxglove]"' in ci


@pytest.mark.timeout(600)
def test_walkthrough_step_by_step(tmp_path):
    pytest.importorskip("foxglove")
    base, fox = _free_ports(2)
    swap = {"19850": str(base), "19851": str(base + 1), "19849": str(base - 1), "8765": str(fox)}

    def command(line: str) -> list[str]:
        for a, b in swap.items():
            line = line.replace(a, b)
        args = shlex.split(line)
        assert args[0] == "cfrace", line
        return [str(BIN / "cfrace"), *args[1:]]

    env = {**os.environ, "COLUMNS": "160"}
    assert blocks()[0][1] == ". .venv/bin/activate"
    steps = blocks()[1:]          # the install step: the environment running this test
    server = None
    done = []
    try:
        for block in steps:
            if block and block[0].startswith("# terminal 2"):
                (line,) = block[1:]
                # Ctrl-C must reach it as in a terminal: a test run started in the background (`... &`)
                # hands its children SIGINT ignored, and Python then keeps it ignored
                server = subprocess.Popen(command(line), cwd=tmp_path, stdout=subprocess.PIPE,
                                          stderr=subprocess.STDOUT, text=True, env=env,
                                          preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
                seen = ""
                while "Ctrl-C" not in seen:       # its banner ends with how to stop it
                    out = server.stdout.readline()
                    assert out, f"sim serve ended: {seen}"
                    seen += out
                assert f"udp://127.0.0.1:{base}" in seen and "obstacles off" in seen
                done.append("serve")
                continue
            if block and block[0].startswith("# refused"):
                # the same flight again on the same server: its drones lie where they landed
                (line,) = block[1:]
                r = subprocess.run(command(line), cwd=tmp_path, capture_output=True, text=True, timeout=120, env=env)
                assert r.returncode == 2 and "not on the start grid for a ground start: cf1 stands at" in r.stderr, \
                    f"{r.returncode}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
                assert r.stderr.count("\n") == 1 and "Traceback" not in r.stderr
                done.append("fly refused")
                server.send_signal(signal.SIGINT)              # "then stop the server"
                try:
                    out, _ = server.communicate(timeout=60)
                except subprocess.TimeoutExpired:
                    server.kill()
                    out, _ = server.communicate()
                    pytest.fail(f"sim serve did not stop on Ctrl-C within 60 s:\n{out[-2000:]}")
                server = None
                continue
            for line in block:
                if line.startswith("#"):
                    continue
                r = subprocess.run(command(line), cwd=tmp_path, capture_output=True, text=True, timeout=300,
                                   env=env)
                # the race ran to its end: both drones finished (no safety stop), exit code 0
                assert r.returncode == 0, f"{line}\n{r.stdout[-2000:]}\n{r.stderr[-2000:]}"
                done.append(line.split()[1] + " " + line.split()[2])
                if line.split()[1] == "fly":
                    assert f"ws://127.0.0.1:{fox}" in r.stderr      # the banner says where to connect
    finally:
        if server is not None:
            server.kill()
            server.communicate()
    assert [d for d in done if d != "serve"][0].startswith("tracks") and "fly refused" in done
    for name in ("dry-run.json", "fly.json"):     # a winner, both drones racing to the end; no safety event acted
        r = json.loads((tmp_path / name).read_text())
        assert r["profile"] == "cf2x_paper" and r["end"] == "finished", (name, r["end"])
        # the winner flew the lap; the race ends at its finish, so the other may be just short of it
        assert next(d for d in r["drones"] if d["name"] == r["winner"])["laps"] == 1, (name, r["drones"])
        assert all(d["gates_passed"] >= 3 for d in r["drones"]), (name, r["drones"])
        assert not [e for e in r["safety_events"] if e["action"] != "none"], (name, r["safety_events"])
    from cfrace.flight.log.writer import read_log
    log = read_log(tmp_path / "fly.mcap")
    assert log.complete and log.count("/foxglove/tf") > 50 and log.meta["uris"][0] == f"udp://127.0.0.1:{base}"
    for name in ("fly_trajectory.png", "fly_speed.png", "fly_timing.png"):
        assert (tmp_path / "plots" / name).stat().st_size > 10_000
    # the speed plot's racing figures are the result's; the replay ("Next") reproduces the flight,
    # its end included (a drone that flew on after the finish)
    import numpy as np

    from cfrace.flight.log.plots import racing_until, trajectories
    from cfrace.rehearsal.replay import replay_log
    until, trajs = racing_until(log), trajectories(log)
    for d in json.loads((tmp_path / "fly.json").read_text())["drones"]:
        tr = trajs[d["body"]]
        speed = np.linalg.norm(tr["vel"], axis=1)[tr["t"] < until[d["body"]]]
        assert abs(float(np.nanmean(speed)) - d["speed_mean"]) < 0.05, (d, until)
    assert replay_log(tmp_path / "fly.mcap")["identical"]
    assert (tmp_path / "lemniscate.png").exists()


def test_the_readme_main_job_is_won_by_ours(tmp_path):
    """The README's first command ends in the main job (a race of the two shipped policies through
    the flight stack); run as written, in lockstep (deterministic), ours wins 3 laps and no
    safety check stops a drone."""
    readme = (ROOT / "README.md").read_text()
    first = re.search(r"```bash\n(.*?)\n```", readme, re.S).group(1)
    job = shlex.split(first.split(" && .venv/bin/")[-1])
    assert job[:3] == ["cfrace", "sim", "dry-run"], job
    job[job.index("--json") + 1] = str(tmp_path / "race.json")
    job[job.index("--log") + 1] = str(tmp_path / "race.mcap")
    p = subprocess.run([sys.executable, "-c", "from cfrace.cli.main import main; main()", *job[1:], "--lockstep",
                        "--quiet"], capture_output=True, text=True, timeout=300)
    assert p.returncode == 0, p.stderr[-800:]
    result = json.loads((tmp_path / "race.json").read_text())
    assert result["end"] == "finished" and result["winner"] == "ego", result["end"]
    ego = next(d for d in result["drones"] if d["name"] == "ego")
    assert ego["method"] == "ours" and ego["laps"] == 3
    assert not [e for e in result["safety_events"] if e["action"] not in ("none", "land_drone", "land_all")
                and e["t"] < ego["lap_times"][-1] + sum(ego["lap_times"][:-1])]
