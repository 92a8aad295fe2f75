"""Where the flight loop's late ticks come from, and the machine's own floor.

    python studies/flight_timing/loop_stalls.py [--seconds 8] [--rt-priority auto|0|N] [--loop-cpu auto] [--bare] [--runs 1]
                                     [--late-ms 0.5]

Default: `cfrace bench loop` (cfrace.rehearsal.loop_timing.bench_loop, the unchanged fly code against a
`cfrace sim serve` process) with a probe around each wait for the next tick
(RealClock.wait_next): for every tick that starts more than ``--late-ms`` late it prints how the wait was
spent by the loop thread, from /proc/self/task/TID/schedstat: on the CPU, waiting in the run queue
for the CPU (another thread or process ran there), and off the CPU without being runnable (asleep,
or waiting for the GIL), and the local timer interrupts per second on each CPU over the run. Linux
only.

--bare: instead, the machine's floor (cfrace.rehearsal.loop_timing.bare_loop, also printed by `cfrace
bench loop`): a loop with no work at all, waiting as the flight loop waits, on the same CPU and
priority: the lateness any 100 Hz Python loop gets on this machine. Used for docs/benchmarks.md
("Loop CPU and priority").
"""

from __future__ import annotations

import argparse
import os
import threading
import time

import numpy as np

from cfrace.flight.loop import clock as ck


def _schedstat() -> tuple[float, float]:
    """(s on the CPU, s waiting in the run queue) of the calling thread."""
    f = open(f"/proc/self/task/{threading.get_native_id()}/schedstat").read().split()
    return int(f[0]) / 1e9, int(f[1]) / 1e9


def timer_interrupts() -> list[int]:
    """Local timer interrupts (the LOC row of /proc/interrupts) so far, per CPU; [] where unreadable."""
    try:
        for line in open("/proc/interrupts"):
            if line.split(":")[0].strip() == "LOC":
                return [int(x) for x in line.split(":")[1].split()[:os.cpu_count() or 1]]
    except (OSError, ValueError):
        pass
    return []


def bare(seconds: float, rt_priority, loop_cpu) -> None:
    from cfrace.rehearsal.loop_timing import bare_loop

    r = bare_loop(seconds, rt_priority=rt_priority, loop_cpu=loop_cpu)
    late = r["late_ms"]
    print(f"bare loop, CPU {r['loop_cpu']}, FIFO {r['rt_fifo']}: late p50 {late['p50']:.3f} p99 {late['p99']:.3f} "
          f"max {late['max']:.3f} ms, jitter p99 {r['period_jitter_ms']['p99']:.3f} ms ({r['ticks']} ticks)")


def probed(seconds: float, rt_priority, loop_cpu, late_ms: float = 0.5) -> None:
    from cfrace.rehearsal.loop_timing import bench_loop

    rec = []
    orig = ck.RealClock.wait_next

    def wait_next(self, before=None, lead_s=0.0):
        r0, q0 = _schedstat()
        p0 = time.perf_counter()
        tick = orig(self, before, lead_s)
        r1, q1 = _schedstat()
        rec.append((tick.k, tick.late_s, time.perf_counter() - p0, r1 - r0, q1 - q0))
        return tick

    ck.RealClock.wait_next = wait_next
    loc0, t0 = timer_interrupts(), time.perf_counter()
    try:
        r = bench_loop(seconds, rt_priority=rt_priority, loop_cpu=loop_cpu)
    finally:
        ck.RealClock.wait_next = orig
    loc = [(b - a) / (time.perf_counter() - t0) for a, b in zip(loc0, timer_interrupts())]
    loop = r["loop"]
    print(f"bench loop, CPU {r['loop_cpu']}, FIFO {r['rt_fifo']}: late p99 {loop['late_ms']['p99']:.3f} max "
          f"{loop['late_ms']['max']:.3f} ms, jitter p99 {loop['period_jitter_p99_ms']:.3f} ms")
    if loc:
        print("  local timer interrupts per s, by CPU (the loop's is " + str(r["loop_cpu"]) + "): "
              + ", ".join(f"{x:.0f}" for x in loc))
    asleep = np.median([w - run - q for _, _, w, run, q in rec]) * 1e3
    print(f"  a wait's time off the CPU and not runnable, median: {asleep:.2f} ms (the sleep)")
    for k, late, wall, run, q in rec:
        if late > late_ms * 1e-3:
            print(f"  tick {k}: {late * 1e3:.3f} ms late; its wait {wall * 1e3:.3f} ms: on the CPU {run * 1e3:.3f}, "
                  f"run queue {q * 1e3:.3f}, off the CPU not runnable {(wall - run - q) * 1e3:.3f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seconds", type=float, default=8.0)
    ap.add_argument("--rt-priority", default="auto", help="auto (50 where permitted), 0 = off, or 1-99")
    ap.add_argument("--loop-cpu", default="auto")
    ap.add_argument("--bare", action="store_true")
    ap.add_argument("--runs", type=int, default=1)
    ap.add_argument("--late-ms", type=float, default=0.5, help="list the ticks that start later than this")
    args = ap.parse_args()
    if not os.path.exists("/proc/self/task"):
        raise SystemExit("loop_stalls.py needs Linux (/proc/self/task/TID/schedstat)")
    print(f"{time.strftime('%Y-%m-%d %H:%M:%S')}, load average {os.getloadavg()[0]:.2f}, {os.cpu_count()} CPUs")
    for _ in range(args.runs):
        if args.bare:
            bare(args.seconds, args.rt_priority, args.loop_cpu)
        else:
            probed(args.seconds, args.rt_priority, args.loop_cpu, args.late_ms)
    print(f"done {time.strftime('%H:%M:%S')}")


if __name__ == "__main__":
    main()
