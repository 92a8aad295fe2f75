"""`cfrace sweep` end to end on a real local Ray instance: a 2 methods x 2 seeds sweep on the
lemniscate (small budgets, several seconds each even on a fast machine, so that one is interrupted) is
killed (SIGKILL to the whole sweep, Ray included), then the same command resumes it: finished runs are
skipped, interrupted ones continue from their checkpoints, and the combined curves are drawn. A run that
fails is tried twice, reported, and the run that needs it is blocked while the others finish. SIGTERM
stops a sweep as Ctrl-C does (one line, exit 143) and it resumes; an address with nothing behind it is
refused in one line."""

from __future__ import annotations

import csv
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

pytest.importorskip("ray")

from cfrace.sweep.parse import load_spec  # noqa: E402

SPEC = """
version: 1
out: {out}
defaults: {{track: lemniscate, threads: 1, envs: 32, steps: 120000, checkpoint_min: 0.02,
           set: {{actor_hidden: [16], critic_hidden: [16]}}}}
grid:
  name: "{{method}}_s{{seed}}"
  method: [ds, ss]
  seed: [0, 1]
runs:   # a run that cannot train (its warm start is no checkpoint: the file's checks only see that the path
        # exists, what it holds is the trainer's to refuse) and one that needs it
  - {{name: broken, method: ds, init_from: /dev/null}}
  - {{name: needs_broken, method: ds, init_from: broken}}
"""


def _ours(out: Path) -> list[int]:
    """Pids of processes whose command line names our output folder (our trainings)."""
    pids = []
    for d in Path("/proc").iterdir():
        if d.name.isdigit():
            try:
                if str(out).encode() in (d / "cmdline").read_bytes():
                    pids.append(int(d.name))
            except OSError:
                pass
    return pids


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_sweep_killed_and_resumed(tmp_path):
    out = tmp_path / "out"
    spec = tmp_path / "ci.yaml"
    spec.write_text(SPEC.format(out=out))
    sweep = load_spec(spec)
    cmd = [sys.executable, "-m", "cfrace", "sweep", str(spec)]
    env = {**os.environ, "COLUMNS": "200"}
    with open(tmp_path / "first.log", "w") as log:
        proc = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, start_new_session=True, env=env)
        try:
            deadline = time.time() + 240
            while not any(r.checkpoint(out).exists() for r in sweep.runs):
                assert proc.poll() is None, (tmp_path / "first.log").read_text()
                assert time.time() < deadline, "no checkpoint after 240 s"
                time.sleep(0.2)
        finally:
            os.killpg(proc.pid, signal.SIGKILL)   # the sweep, Ray's gcs/raylet/agents: all of its group
            proc.wait()
    deadline = time.time() + 60
    while _ours(out) and time.time() < deadline:   # trainings get SIGTERM when their worker dies
        time.sleep(0.5)
    assert not _ours(out), "trainings left running after the sweep was killed"
    grid = [r for r in sweep.runs if "broken" not in r.name]
    before = {r.name: (r.started(out), r.trained(out)) for r in grid}
    assert any(s and not t for s, t in before.values()), before   # at least one run was interrupted
    assert not all(t for _, t in before.values())

    res = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=300)
    assert res.returncode == 1, res.stdout[-3000:] + res.stderr[-3000:]   # broken failed
    for r in grid:
        assert r.done(out), r.name
        rows = list(csv.DictReader(open(r.out_dir(out) / "metrics.csv")))
        assert [int(x["iteration"]) for x in rows] == list(range(1, len(rows) + 1))   # no gap, no repeat
        assert int(rows[-1]["env_steps"]) >= 120000
        resumed = "(resumed)" in (r.out_dir(out) / "train.log").read_text()
        assert resumed == (before[r.name][0] and not before[r.name][1]), r.name
    summary = res.stdout[res.stdout.index("sweep summary"):]
    for name, (started, trained) in before.items():
        what = "skip" if trained else ("resume" if started else "start")
        assert any(line.split("│")[1:4] and name in line and what in line for line in summary.splitlines()), \
            (name, what, summary)
    rows = {line.split("│")[1].strip(): [c.strip() for c in line.split("│")[2:5]]
            for line in summary.splitlines() if line.count("│") >= 5}
    assert rows["broken"] == ["failed", "start", "2"] and rows["needs_broken"][0] == "blocked"
    assert "broken: cfrace train exited with code 2" in res.stdout and "needs broken" in res.stdout
    assert "/dev/null: not a cfrace training checkpoint" in (out / "broken" / "train.log").read_text()
    assert not (out / "needs_broken").exists()
    assert (out / "curves.png").stat().st_size > 10_000
    assert "combined training curves" in res.stdout and "the time one after another" in res.stdout


def test_without_ray_says_how_to_get_it(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC.format(out=tmp_path / "out"))
    code = ("import sys; sys.modules['ray'] = None; from cfrace.cli.main import main; "
            f"sys.argv = ['cfrace', 'sweep', {str(spec)!r}]; main()")
    res = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert res.returncode == 2
    last = res.stderr.strip().splitlines()[-1]
    assert last == 'error: this needs Ray: pip install "cfrace[cluster]" (or pip install ray)'
    assert "Traceback" not in res.stderr and not (tmp_path / "out").exists()


def _free_port() -> int:
    import socket

    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def test_an_address_with_nothing_behind_it_is_one_line(tmp_path):
    spec = tmp_path / "s.yaml"
    spec.write_text(SPEC.format(out=tmp_path / "out"))
    port = _free_port()
    t0 = time.time()
    res = subprocess.run([sys.executable, "-m", "cfrace", "sweep", str(spec), "--address", f"127.0.0.1:{port}"],
                         capture_output=True, text=True, timeout=60)
    assert res.returncode == 2 and time.time() - t0 < 30, res.stderr
    assert res.stderr == (f"error: --address 127.0.0.1:{port}: nothing answers at 127.0.0.1:{port} (Connection "
                          f"refused); is the Ray head running (`ray start --head`)?\n")
    assert not (tmp_path / "out").exists()


def test_sigterm_raises_keyboard_interrupt_and_restores_the_handler():
    from cfrace.sweep.ray_exec import sigterm_stops

    before = signal.getsignal(signal.SIGTERM)
    with pytest.raises(KeyboardInterrupt, match="^SIGTERM$"):
        with sigterm_stops():
            os.kill(os.getpid(), signal.SIGTERM)
            time.sleep(5)
    with pytest.raises(KeyboardInterrupt, match="^$"):   # Ctrl-C stays Ctrl-C
        with sigterm_stops():
            raise KeyboardInterrupt
    assert signal.getsignal(signal.SIGTERM) is before


ONE_RUN = """
version: 1
out: {out}
defaults: {{track: lemniscate, threads: 1, envs: 32, steps: 60000, checkpoint_min: 0.02,
           set: {{actor_hidden: [16], critic_hidden: [16]}}}}
runs: [{{name: a, method: ds}}]
"""


@pytest.mark.slow
@pytest.mark.timeout(400)
def test_sigterm_stops_the_sweep_and_it_resumes(tmp_path):
    """SIGTERM to the sweep alone (as `kill PID`): one "stopped" line, exit 143, none of Ray's own
    signal dump, no training left behind; the same command then finishes the run from its checkpoint."""
    out = tmp_path / "out"
    spec = tmp_path / "one.yaml"
    spec.write_text(ONE_RUN.format(out=out))
    (run,) = load_spec(spec).runs
    cmd = [sys.executable, "-m", "cfrace", "sweep", str(spec)]
    with open(tmp_path / "out.log", "w") as log, open(tmp_path / "err.log", "w") as err:
        proc = subprocess.Popen(cmd, stdout=log, stderr=err, start_new_session=True)
        try:
            deadline = time.time() + 240
            while not run.checkpoint(out).exists():
                assert proc.poll() is None and time.time() < deadline, (tmp_path / "err.log").read_text()
                time.sleep(0.2)
            proc.send_signal(signal.SIGTERM)
            code = proc.wait(timeout=60)
        finally:
            if proc.poll() is None:
                os.killpg(proc.pid, signal.SIGKILL)
                proc.wait()
    stdout, stderr = (tmp_path / "out.log").read_text(), (tmp_path / "err.log").read_text()
    assert code == 143, stdout[-2000:] + stderr
    assert stderr.strip().splitlines()[-1:] == ["sweep stopped (SIGTERM); run the same command again to resume"] \
        and "Traceback" not in stderr, stderr
    assert "SIGTERM received" not in stdout + stderr and "PC: @" not in stdout + stderr
    deadline = time.time() + 60
    while _ours(out) and time.time() < deadline:
        time.sleep(0.5)
    assert not _ours(out), "trainings left running after the sweep was stopped"
    assert run.started(out) and not run.trained(out)
    res = subprocess.run(cmd, capture_output=True, text=True, env={**os.environ, "COLUMNS": "200"}, timeout=300)
    assert res.returncode == 0, res.stdout[-3000:] + res.stderr[-3000:]
    assert run.done(out) and "(resumed)" in (out / "a" / "train.log").read_text()
    rows = list(csv.DictReader(open(out / "a" / "metrics.csv")))
    assert [int(x["iteration"]) for x in rows] == list(range(1, len(rows) + 1))
