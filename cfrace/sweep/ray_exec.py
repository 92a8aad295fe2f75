"""Run a sweep on Ray: a local instance (one run per core) or a cluster (``address``).

Each run is one Ray task that brings the run to done exactly as the local executor does
(cfrace.sweep.local.train_and_export: a `cfrace train` process, started or resumed, then the
export), so a sweep and `run_local` leave the same folders. The task asks Ray for as many CPUs
as the run's torch threads. The driver submits a run once its dependencies are done, retries a
failed run up to ``retries`` times, marks the runs that depend on a failed one as blocked, and
calls ``on_update`` about once a second for the progress view. On a cluster, OUT must be on a
filesystem every node sees, and every node needs cfrace installed.
"""

from __future__ import annotations

import contextlib
import logging
import os
import signal
import socket
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Callable

from cfrace.errors import ConfigError
from cfrace.sweep.local import train_and_export
from cfrace.sweep.progress import RunState
from cfrace.sweep.spec import Run, Sweep

INSTALL_HINT = 'this needs Ray: pip install "cfrace[cluster]" (or pip install ray)'


def require_ray():
    """The ray module, or a one-line ConfigError saying how to get it."""
    try:
        import ray
    except ImportError:
        raise ConfigError(INSTALL_HINT) from None
    return ray


def init_ray(address: str | None = None, cpus: int | None = None):
    """Connect to ``address`` or start a local instance with ``cpus`` CPUs (default: every core)."""
    ray = require_ray()
    if ray.is_initialized():
        return ray
    kw = dict(include_dashboard=False, log_to_driver=False, logging_level=logging.ERROR,
              configure_logging=True)
    if address:
        check_address(address)
    try:
        if address:
            ray.init(address=address, **kw)
        else:
            # "local": always a new instance of our own, never a cluster left running on this machine
            ray.init(address="local", num_cpus=cpus or os.cpu_count() or 1, **kw)
    except ConnectionError as exc:
        raise ConfigError(f"--address {address}: cannot connect to a Ray cluster ({str(exc).splitlines()[0]}; a "
                          f"cluster started with `ray start` wants RAY_AUTH_MODE=token and its ~/.ray/auth_token)") \
            from None
    return ray


def check_address(address: str, timeout_s: float = 3.0) -> None:
    """A one-line ConfigError unless something accepts a TCP connection on the address's port within
    ``timeout_s`` (ray.init would retry an address with nothing behind it for minutes, warning)."""
    if address in ("auto", "local"):   # Ray's own look-ups, no port to try
        return
    host, _, port = address.split("://", 1)[-1].rpartition(":")
    if not host or not port.isdigit():
        raise ConfigError(f"--address {address}: expected HOST:PORT or ray://HOST:PORT")
    try:
        socket.create_connection((host.strip("[]"), int(port)), timeout=timeout_s).close()
    except OSError as exc:
        raise ConfigError(f"--address {address}: nothing answers at {host}:{port} ({exc.strerror or exc}); "
                          f"is the Ray head running (`ray start --head`)?") from None


@contextlib.contextmanager
def sigterm_stops():
    """SIGTERM raises KeyboardInterrupt("SIGTERM") in the main thread, so it stops the driver as Ctrl-C
    does (the flight stack's convention; `cfrace sweep` exits 143 on it). Entered after ray.init, it also
    takes SIGTERM back from the crash handler Ray's core worker installs (a "*** SIGTERM received ...
    PC: @" dump)."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    got = []

    def stop(signum, frame):
        got.append(signum)
        raise KeyboardInterrupt("SIGTERM")

    old = signal.signal(signal.SIGTERM, stop)
    try:
        yield
    except KeyboardInterrupt:
        if got:   # ray.wait turns the handler's exception into a bare KeyboardInterrupt
            raise KeyboardInterrupt("SIGTERM") from None
        raise
    finally:
        signal.signal(signal.SIGTERM, old)


def run_threads(run: Run) -> int:
    """CPUs a run uses: its torch threads (1 by default, as `cfrace train`)."""
    return max(1, int(run.options.get("threads") or 1))


@dataclass
class SweepReport:
    states: list[RunState]
    wall_s: float                     #: the sweep's wall time
    run_wall_s: float = 0.0           #: the runs' own times added up (one after another)
    failed: list[str] = field(default_factory=list)
    blocked: list[str] = field(default_factory=list)

    @property
    def ok(self) -> bool:
        return not self.failed and not self.blocked


def _task_body(run: Run, out_root: str) -> dict:
    """What a Ray worker runs: one run to done, output in OUT/NAME/train.log."""
    return train_and_export(run, out_root, run.out_dir(out_root) / "train.log")


class _Scheduler:
    """The driver's bookkeeping: which run goes when, what came back, what is blocked."""

    def __init__(self, ray, sweep: Sweep, out_root: str, retries: int):
        self.ray, self.out_root, self.retries = ray, out_root, retries
        self.task = ray.remote(max_retries=0)(_task_body)
        self.states = {r.name: RunState(r) for r in sweep.runs}
        self.running: dict = {}   # ObjectRef -> run name
        for s in self.states.values():
            if s.run.done(out_root):
                s.state, s.action = "done", "skip"

    def submit_ready(self) -> None:
        """Submit every waiting run whose dependencies are done; notice queued runs that started."""
        for s in self.states.values():
            if s.state == "waiting" and all(self.states[d].state == "done" for d in s.run.deps):
                s.attempts += 1
                s.state, s.started_s, s.submitted = "queued", None, time.time()
                ref = self.task.options(num_cpus=run_threads(s.run), name=f"cfrace-{s.run.name}").remote(
                    s.run, self.out_root)
                self.running[ref] = s.run.name
            elif s.state == "queued":
                s.poll_started(self.out_root)

    def collect(self, ref) -> None:
        """A task returned: done, back to waiting for another try, or failed (dependents blocked)."""
        s = self.states[self.running.pop(ref)]
        try:
            rep = self.ray.get(ref)
            s.action, s.error = rep["action"], rep["error"]
            s.wall_s += rep["wall_s"]
        except Exception as exc:   # the worker died (killed, out of memory, node lost)
            s.error = f"task failed: {type(exc).__name__}: {str(exc).splitlines()[0][:160]}"
            s.wall_s += time.time() - (s.started_s or s.submitted)
        s.started_s = None
        if s.error is None:
            s.state = "done"
        elif s.attempts <= self.retries:
            s.state = "waiting"      # submitted again: resumes from its checkpoint
        else:
            s.state = "failed"
            self.block_dependents(s.run.name)

    def block_dependents(self, name: str) -> None:
        for s in self.states.values():
            if name in s.run.deps and s.state == "waiting":
                s.state, s.error = "blocked", f"needs {name}"
                self.block_dependents(s.run.name)


def run_ray(sweep: Sweep, out_root: str | Path | None = None, address: str | None = None, cpus: int | None = None,
            retries: int = 1, on_update: Callable[[list[RunState]], None] | None = None,
            poll_s: float = 1.0) -> SweepReport:
    """Run the sweep on Ray; returns when every run is done, failed or blocked by a failed one. Ctrl-C
    or SIGTERM raise KeyboardInterrupt (str "SIGTERM" for the latter); the runs go on from their
    checkpoints when the sweep is run again."""
    ray = init_ray(address, cpus)
    out_root = str(out_root if out_root is not None else sweep.out)
    total = int(ray.cluster_resources().get("CPU", 0))
    for r in sweep.runs:
        if run_threads(r) > total:
            raise ConfigError(f"{sweep.path}: {r.name} ({r.source}) asks for {run_threads(r)} threads, the Ray "
                              f"instance has {total} CPUs")
    t0 = time.perf_counter()
    sched = _Scheduler(ray, sweep, out_root, retries)
    with sigterm_stops():
        while True:
            sched.submit_ready()
            if on_update is not None:
                on_update(list(sched.states.values()))
            if not sched.running:
                break
            ready, _ = ray.wait(list(sched.running), num_returns=1, timeout=poll_s)
            for ref in ready:
                sched.collect(ref)
    states = list(sched.states.values())
    return SweepReport(states, time.perf_counter() - t0, sum(s.wall_s for s in states),
                       [s.run.name for s in states if s.state == "failed"],
                       [s.run.name for s in states if s.state == "blocked"])
