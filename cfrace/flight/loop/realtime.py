"""Scheduling of the flight process for a steady 100 Hz: a CPU of its own for the loop thread and
SCHED_FIFO where the process may use it.

Loop CPU (``loop_cpu``, default "auto"): the loop thread is pinned to one CPU and every other
thread of the process (cflib's receive and packet threads, the mocap reader, the log's fsync
thread, an in-process simulator) to the remaining CPUs, so that none of them competes with the
loop for its CPU. "auto" takes the highest CPU this process may use when it may use two or
more (on one CPU there is nothing to separate); "off" leaves scheduling to the OS; a number names
the CPU. `cfrace bench loop` also keeps its simulated drones (the `cfrace sim serve` process) off
that CPU, as real drones compute on their own hardware. Measured on the 2-core development
machine: docs/benchmarks.md, "Loop CPU and priority".

Real-time priority (``rt_priority``, default "auto"): "auto" runs the loop thread SCHED_FIFO at
AUTO_RT_PRIORITY (and the process's other threads one below) when the process may (root,
CAP_SYS_NICE or an RLIMIT_RTPRIO of at least that), and at normal priority otherwise; 0 is off; 1-99
names the priority. Whether it took effect is in every result (``rt_fifo``).

Only Linux has per-thread affinity (os.sched_setaffinity); elsewhere pinning is a no-op and says so
in the result (``loop_cpu: null``).
"""

from __future__ import annotations

import os
import threading

from cfrace.errors import ConfigError

AUTO, OFF = "auto", "off"
AUTO_RT_PRIORITY = 50   #: SCHED_FIFO priority of the loop thread with rt_priority "auto"


def allowed_cpus() -> set[int]:
    """The CPUs this process may run on (all of os.cpu_count() where affinity is unknown)."""
    if hasattr(os, "sched_getaffinity"):
        return set(os.sched_getaffinity(0))
    return set(range(os.cpu_count() or 1))


def parse_loop_cpu(value) -> int | str:
    """"auto" / "off" / a CPU index (int or digits) -> the normalised setting; ConfigError otherwise."""
    if isinstance(value, bool):
        raise ConfigError(f"loop_cpu: expected auto, off or a CPU number, got {value!r}")
    if isinstance(value, int):
        if value < 0:
            raise ConfigError(f"loop_cpu: a CPU number is >= 0, got {value}")
        return value
    text = str(value).strip().lower()
    if text in (AUTO, OFF):
        return text
    if text.isdigit():
        return int(text)
    raise ConfigError(f"loop_cpu: expected auto, off or a CPU number, got {value!r}")


def resolve_loop_cpu(setting) -> int | None:
    """The CPU the loop thread goes to for ``setting`` on this machine, or None (no pinning)."""
    setting = parse_loop_cpu(setting)
    if setting == OFF or not hasattr(os, "sched_setaffinity"):
        return None
    cpus = allowed_cpus()
    if setting == AUTO:
        return max(cpus) if len(cpus) >= 2 else None
    if setting not in cpus:
        raise ConfigError(f"loop_cpu: CPU {setting} is not available to this process "
                          f"(it may use {', '.join(str(c) for c in sorted(cpus))})")
    if len(cpus) < 2:
        raise ConfigError(f"loop_cpu: this process may use CPU {setting} only; pinning needs two or more CPUs "
                          f"(use auto or off)")
    return setting


def other_cpus(loop_cpu: int | None) -> set[int] | None:
    """The CPUs for everything but the loop thread (None when the loop is not pinned)."""
    if loop_cpu is None:
        return None
    return allowed_cpus() - {loop_cpu}


def _thread_ids() -> list[int]:
    """Native ids of every thread of this process (Python's and native ones, Linux /proc), else
    the Python threads'."""
    try:
        return [int(t) for t in os.listdir("/proc/self/task")]
    except OSError:
        return [t.native_id for t in threading.enumerate() if t.native_id is not None]


def pin_loop_thread(loop_cpu: int | None) -> list | None:
    """Pin the calling (loop) thread to ``loop_cpu`` and every other thread of the process to the
    other CPUs. Returns [(tid, old CPU set)] to give to ``restore_affinity``, or None when nothing
    was pinned (no CPU given, or the OS refused the loop thread's: the flight goes on unpinned).
    Threads that end meanwhile are skipped."""
    if loop_cpu is None:
        return None
    me = threading.get_native_id()
    rest = other_cpus(loop_cpu)
    try:
        changed = [(0, set(os.sched_getaffinity(0)))]
        os.sched_setaffinity(0, {loop_cpu})
    except OSError:
        return None
    for tid in _thread_ids():
        if tid == me:
            continue
        try:
            old = set(os.sched_getaffinity(tid))
            os.sched_setaffinity(tid, rest)
            changed.append((tid, old))
        except OSError:
            pass   # that thread ended
    return changed


def restore_affinity(changed: list | None) -> None:
    for tid, cpus in changed or []:
        try:
            os.sched_setaffinity(tid, cpus)
        except OSError:
            pass   # that thread has ended


def parse_rt_priority(value) -> int | str:
    """"auto" / 0 (off) / 1-99 (int or digits) -> the normalised setting; ConfigError otherwise."""
    if isinstance(value, bool):
        raise ConfigError(f"rt_priority: expected auto or a priority 0-99, got {value!r}")
    text = str(value).strip().lower()
    if text == AUTO:
        return AUTO
    if isinstance(value, int) or text.isdigit():
        prio = int(text)
        if 0 <= prio <= 99:
            return prio
        raise ConfigError(f"rt_priority: must be in [0, 99], got {prio}")
    raise ConfigError(f"rt_priority: expected auto or a priority 0-99, got {value!r}")


def resolve_rt_priority(setting) -> int:
    """The SCHED_FIFO priority to ask for (0: none): "auto" -> AUTO_RT_PRIORITY (set_fifo leaves
    the scheduling alone where that is not permitted)."""
    setting = parse_rt_priority(setting)
    return AUTO_RT_PRIORITY if setting == AUTO else setting


def set_fifo(priority: int) -> list | None:
    """SCHED_FIFO for the calling (loop) thread at ``priority`` and for the process's other threads
    (cflib's receive/ping/packet threads, the mocap reader) one below, so a thread holding the GIL
    is never preempted by the machine's ordinary jobs while the loop waits for it (Linux, needs
    root or CAP_SYS_NICE). Returns [(tid, old policy, old param)] to restore, or None."""
    if priority <= 0 or not hasattr(os, "sched_setscheduler"):
        return None
    me = threading.get_native_id()
    changed = []
    try:
        for th in [threading.current_thread()] + [t for t in threading.enumerate() if t.native_id != me]:
            tid = 0 if th.native_id == me else th.native_id
            if tid is None:
                continue
            old = (os.sched_getscheduler(tid), os.sched_getparam(tid))
            os.sched_setscheduler(tid, os.SCHED_FIFO, os.sched_param(priority if tid == 0 else max(1, priority - 1)))
            changed.append((tid, *old))
    except (OSError, PermissionError):
        if not changed:
            return None
    return changed


def restore_scheduler(changed: list | None) -> None:
    for tid, policy, param in changed or []:
        try:
            os.sched_setscheduler(tid, policy, param)
        except OSError:
            pass   # that thread has ended
