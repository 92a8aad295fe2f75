"""Loop clocks: absolute deadlines in real time, or a lockstep clock that drives a simulator.

RealClock: tick k is due at t0 + k dt (absolute deadlines: no drift, no accumulation of sleep
overshoot). A tick that starts late never causes a burst: when the previous tick overran one or
more deadlines, those ticks are SKIPPED (counted) and the loop runs the newest due tick once,
with fresh mocap data. Without a warm-up, waiting is a plain sleep.
``wait_next(before, lead_s)`` sleeps until ``lead_s`` ahead of the deadline, then calls
``before()`` again and again while one more call still ends ``WARM_GUARD_S`` before the deadline
(at most ``WARM_MAX_CALLS`` times), then waits out the rest without sleeping (``os.sched_yield()``
in a loop: it lets cflib's and the mocap's threads take the GIL but keeps the CPU): the flight loop
keeps its code and data warm with it (FlightLoop.prewarm). On this VM anything the loop does after
a real sleep, even one of 0.1 ms, runs several times slower (docs/benchmarks.md, "What each warm-up pays").
Not ``time.sleep(0)``: that arms a timer on every call (one timer interrupt each; on this VM a call
can take 0.1 ms), ``sched_yield`` arms none (docs/benchmarks.md, "Against the commit before the
consolidation").

LockstepClock: no waiting at all; every wait_next() advances the simulated drones by exactly one
period (or by a requested stall) and the loop's time is k dt.
"""

from __future__ import annotations

import math
import os
import time
from dataclasses import dataclass

WARM_GUARD_S = 1e-4     #: the last warm-up call ends at least this long before the deadline
WARM_MAX_CALLS = 64     #: warm-up calls per tick at most


@dataclass(frozen=True)
class Tick:
    k: int          #: tick index (k dt after the start)
    t: float        #: s since the start, the loop's clock (race time)
    late_s: float   #: s this tick started after the deadline it was expected at
    skipped: int    #: deadlines skipped before this tick (overrun)
    wall: float     #: time.perf_counter() when the tick started (real) / t (lockstep)


class RealClock:
    def __init__(self, dt: float, *, perf=time.perf_counter, sleep=time.sleep, yield_cpu=None):
        self.dt = float(dt)
        self._perf, self._sleep = perf, sleep
        #: the final wait's call: gives up the GIL, not the CPU (sleep(0) where there is no sched_yield)
        self._yield = yield_cpu or getattr(os, "sched_yield", None) or (lambda: sleep(0))
        self.t0 = math.nan
        self._k_next = 0
        self.skipped = 0
        self.realtime = True

    def start(self) -> None:
        self.t0 = self._perf()
        self._k_next = 0

    def now(self) -> float:
        """s since start on the loop clock."""
        return self._perf() - self.t0

    @property
    def next_k(self) -> int:
        """Index of the tick the next wait_next() is due for (before any skip)."""
        return self._k_next

    def wait_next(self, before=None, lead_s: float = 0.0) -> Tick:
        """Wait for the next deadline (see the module doc)."""
        k = self._k_next
        deadline = self.t0 + k * self.dt
        now = self._perf()
        if before is not None and now < deadline - lead_s:
            self._sleep(deadline - lead_s - now)
            # repeat while the next call (no longer than the last one: they get faster as the caches
            # fill) still ends WARM_GUARD_S before the deadline
            end = deadline - WARM_GUARD_S
            a = self._perf()
            for _ in range(WARM_MAX_CALLS):
                before()
                b = self._perf()
                if b + (b - a) > end:
                    break
                a = b
            now = self._perf()
            while now < deadline:    # stay on the CPU: a real sleep here undoes the warm-up
                self._yield()        # lets cflib's and the mocap's threads take the GIL meanwhile
                now = self._perf()
        if now < deadline:
            self._sleep(deadline - now)
            now = self._perf()
        late = now - deadline
        skipped = 0
        if late >= self.dt:                      # overrun: run the newest due tick, drop the rest
            k_due = int((now - self.t0) / self.dt)
            skipped = max(0, k_due - k)
            k = k + skipped
            self.skipped += skipped
        self._k_next = k + 1
        return Tick(k, now - self.t0, late, skipped, now)

    def stall(self, seconds: float) -> None:
        """Fault injection: block the loop (real time: really sleep)."""
        self._sleep(seconds)


class LockstepClock:
    """Virtual time for --lockstep: ``advance(dt)`` moves the simulated world one tick."""

    def __init__(self, dt: float, advance=None, warm_calls: int = 0):
        self.dt = float(dt)
        self._advance = advance
        self.warm_calls = int(warm_calls)   #: before() calls per tick (tests: the warm-up changes nothing)
        self._k = self._now_k = -1
        self._stall = 0.0
        self.skipped = 0
        self.realtime = False

    def start(self) -> None:
        self._k = self._now_k = -1

    def now(self) -> float:
        return max(self._now_k, 0) * self.dt

    @property
    def next_k(self) -> int:
        return self._k + 1

    def wait_next(self, before=None, lead_s: float = 0.0) -> Tick:
        """One tick on. ``before`` is called ``warm_calls`` times (0 by default: no wall-clock wait
        to use) after the world moved and with now() at the new tick, as the real-time warm-up
        runs just before the deadline."""
        late, skipped = 0.0, 0
        if self._k >= 0:
            if self._stall > 0.0:
                # the loop "hung" for _stall s: the world moved on without us
                skipped = int(self._stall / self.dt)
                late = self._stall
                self._stall = 0.0
            if self._advance is not None:
                self._advance(self.dt * (1 + skipped))
            self._now_k = self._k + 1 + skipped
            if before is not None and skipped == 0 and self.warm_calls:
                for _ in range(self.warm_calls):
                    before()
        self._k += 1 + skipped
        self._now_k = self._k
        self.skipped += skipped
        t = self._k * self.dt
        return Tick(self._k, t, late, skipped, t)

    def stall(self, seconds: float) -> None:
        self._stall += float(seconds)
