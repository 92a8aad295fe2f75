"""Run a sweep's runs one after another on this machine, resuming where an earlier call stopped.

Each run is its own `cfrace train` process (the argument list Run.train_argv prints), so a run
behaves exactly as when started by hand: same folder, logs, checkpoints, Ctrl-C handling.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Callable

from cfrace.errors import CfraceError
from cfrace.sweep.spec import Run, Sweep


class SweepError(CfraceError):
    """A run of a sweep failed or was stopped before its budget was spent."""


def cfrace_argv(argv: list[str]) -> list[str]:
    """The command line that runs `cfrace ARGV...` with this interpreter."""
    return [sys.executable, "-m", "cfrace", *argv]


def _die_with_parent() -> None:  # pragma: no cover - runs in the child before exec
    """Linux: the child gets SIGTERM when the process that started it dies (a killed sweep leaves no
    orphan training behind; SIGTERM makes `cfrace train` checkpoint and exit)."""
    try:
        import ctypes

        ctypes.CDLL("libc.so.6", use_errno=True).prctl(1, signal.SIGTERM)  # PR_SET_PDEATHSIG
    except OSError:
        pass


def start_command(run: Run, out_root: str | Path) -> tuple[str, list[str]]:
    """("start" | "resume", argv) for a run that is not trained yet."""
    if run.started(out_root):
        return "resume", run.resume_argv(out_root)
    return "start", run.train_argv(out_root)


def execute(argv: list[str], log: Path | None = None, env: dict | None = None) -> int:
    """Run `cfrace ARGV` to its end; output to ``log`` (appended) or inherited. Returns the exit code."""
    full_env = {**os.environ, **(env or {})}
    if log is None:
        return subprocess.run(cfrace_argv(argv), env=full_env, preexec_fn=_die_with_parent).returncode
    log.parent.mkdir(parents=True, exist_ok=True)
    with open(log, "a") as fh:
        fh.write(f"\n$ cfrace {' '.join(argv)}\n")
        fh.flush()
        return subprocess.run(cfrace_argv(argv), stdout=fh, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                              env=full_env, preexec_fn=_die_with_parent).returncode


def train_and_export(run: Run, out_root: str | Path, log: Path | None = None, env: dict | None = None) -> dict:
    """Bring one run to done: start or resume its training, then export. Returns a small report
    {name, action, exit_code, trained, exported, wall_s, error}; never raises for a failed run."""
    t0 = time.perf_counter()
    report = {"name": run.name, "action": "skip", "exit_code": 0, "trained": False, "exported": False,
              "wall_s": 0.0, "error": None}
    if not run.trained(out_root):
        action, argv = start_command(run, out_root)
        report["action"] = action
        code = execute(argv, log, env)
        report["exit_code"] = code
        if code != 0:
            report["error"] = f"cfrace train exited with code {code}"
    report["trained"] = run.trained(out_root)
    if report["error"] is None and not report["trained"]:
        report["error"] = "stopped before its budget was spent (checkpointed; resume the sweep)"
    if report["trained"] and run.export is not None and not run.done(out_root):
        code = execute(run.export_argv(out_root), log, env)
        if code != 0:
            report["exit_code"], report["error"] = code, f"cfrace export exited with code {code}"
    report["exported"] = run.export is not None and run.done(out_root)
    report["wall_s"] = time.perf_counter() - t0
    return report


def run_local(sweep: Sweep, out_root: str | Path | None = None,
              post_run: Callable[[Run, Path], None] | None = None,
              echo: Callable[[str], None] = print, log_dir: bool = False) -> list[dict]:
    """Run every run of ``sweep`` in dependency order, one at a time, in this machine's processes.

    Finished runs (budget spent, exported if they export) are skipped; interrupted ones continue with
    `cfrace train --resume` for the rest of their budget. ``post_run(run, out_dir)`` is called for
    every run once it is done, in order, also for runs finished by an earlier call (make it
    idempotent). With ``log_dir`` each run's output goes to OUT/NAME/train.log instead of the
    terminal. Raises SweepError at the first run that fails; the runs before it stay done.
    """
    out_root = Path(out_root if out_root is not None else sweep.out)
    reports = []
    for run in sweep.runs:
        out_dir = run.out_dir(out_root)
        if run.done(out_root):
            echo(f"{run.name}: done")
        else:
            action = start_command(run, out_root)[0] if not run.trained(out_root) else "export"
            echo(f"{run.name}: {action}")
            report = train_and_export(run, out_root, out_dir / "train.log" if log_dir else None)
            reports.append(report)
            if report["error"]:
                raise SweepError(f"run {run.name} ({run.source}): {report['error']}")
        if post_run is not None:
            post_run(run, out_dir)
    return reports
