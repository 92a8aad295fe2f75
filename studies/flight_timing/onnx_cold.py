"""How long one ONNX inference of the paper-size actor takes back to back and after a sleep.

    python studies/flight_timing/onnx_cold.py [--calls 300]

The flight loop sleeps most of each 10 ms period; this measures what that costs the next inference
(docs/benchmarks.md, "What each warm-up pays"). Actor: the hold controller inside an MLP of
the paper's size [512, 512, 256, 128] (cfrace.rehearsal.hold_policy), run through cfrace.policy.OnnxPolicy
as the loop runs it. Prints p50 / p90 / p99 in microseconds per sleep length, and the same with a
warm-up call 1 ms before each timed call (the loop's previous warm-up), with a busy loop instead of
the sleep, and through the loop's own clock with its warm-up window (cfrace.flight.loop.clock.RealClock:
calls over and over from 3 ms before the deadline, then no sleep).
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

from cfrace.flight.loop.clock import RealClock
from cfrace.rehearsal.hold_policy import make_sized_hold_policy
from cfrace.policy import OnnxPolicy


def timed_calls(policy, obs, period_s: float, calls: int, warm_lead_s: float = 0.0, mode: str = "once") -> np.ndarray:
    """Time one call per period. mode: "once" (one warm-up call warm_lead_s before the deadline, then
    sleep), "spin" (no call: a busy loop instead of the sleep for the whole period), "window" (the
    flight loop's own clock, cfrace.flight.loop.clock.RealClock, with its warm-up window of warm_lead_s)."""
    out = []
    if mode == "window":
        clock = RealClock(period_s)
        clock.start()
        for _ in range(calls):
            clock.wait_next(before=lambda: policy(obs), lead_s=warm_lead_s)
            a = time.perf_counter()
            policy(obs)
            out.append(time.perf_counter() - a)
        return np.asarray(out) * 1e6
    t0 = time.perf_counter()
    for k in range(1, calls + 1):
        deadline = t0 + k * period_s
        if mode == "spin":
            while time.perf_counter() < deadline:
                pass
        elif warm_lead_s > 0.0:
            now = time.perf_counter()
            if now < deadline - warm_lead_s:
                time.sleep(deadline - warm_lead_s - now)
            policy(obs)
        now = time.perf_counter()
        if now < deadline:
            time.sleep(deadline - now)
        a = time.perf_counter()
        policy(obs)
        out.append(time.perf_counter() - a)
    return np.asarray(out) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--calls", type=int, default=300)
    args = ap.parse_args()
    with tempfile.TemporaryDirectory() as tmp:
        policy = OnnxPolicy(make_sized_hold_policy(Path(tmp) / "p.onnx", "race42", "lemniscate", False))
        obs = np.random.default_rng(0).normal(size=(1, 42)).astype(np.float32)
        policy(obs)
        print(f"{'case':34s} {'p50 us':>8s} {'p90 us':>8s} {'p99 us':>8s}")
        cases = [("back to back", 0.0, 0.0)] + [(f"every {p * 1e3:g} ms (sleep between)", p, 0.0)
                                                for p in (0.001, 0.005, 0.01)]
        cases = [(n, p, lead, "once") for n, p, lead in cases]
        cases += [("every 10 ms, warm-up 1 ms before", 0.01, 0.001, "once"),
                  ("every 10 ms, busy loop, no sleep", 0.01, 0.0, "spin"),
                  ("every 10 ms, 3-ms warm-up window", 0.01, 0.003, "window")]
        for name, period, lead, mode in cases:
            v = timed_calls(policy, obs, period, args.calls, lead, mode)
            p50, p90, p99 = np.percentile(v, [50, 90, 99])
            print(f"{name:34s} {p50:8.0f} {p90:8.0f} {p99:8.0f}")


if __name__ == "__main__":
    main()
