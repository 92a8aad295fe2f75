"""The flight loop's timing figures, one definition each, computed by one function
(``loop_figures``) for the live result table, the JSON result, `cfrace log info` and the timing
plot of `cfrace log plot`.

Per tick (the loop's TickTimes, or a flight log's /timing messages):
  period   start of this tick minus start of the previous one (the first tick has none); a tick
           that skipped deadlines has a period of (1 + skipped) periods plus its lateness
  jitter   |period - dt|
  late     start minus the deadline the tick was due at
  compute  start to the last setpoint handed to the links
and per drone the observation and ONNX times of the ticks it inferred on.
A tick's start is its time on the loop clock (Tick.t; the log's "t" of /timing), so a log gives the
same periods as the live loop: never negative, whatever the lateness (older code added late_s
to t a second time).
"""

from __future__ import annotations

import numpy as np

from cfrace.flight.config import DRONE_NAMES


def periods(start_s) -> np.ndarray:
    """(N,) s between consecutive tick starts; NaN for the first tick."""
    start = np.asarray(start_s, dtype=np.float64)
    return np.concatenate([[np.nan], np.diff(start)]) if start.size else np.zeros(0)


def ms_stats(x) -> dict:
    """p50 / p99 / max in ms of the finite values of x (s); None where there are none."""
    x = np.asarray(x, dtype=np.float64)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"p50": None, "p99": None, "max": None}
    return {"p50": round(float(np.percentile(x, 50)) * 1e3, 4), "p99": round(float(np.percentile(x, 99)) * 1e3, 4),
            "max": round(float(x.max()) * 1e3, 4)}


def loop_figures(timing: dict, dt: float, names: list[str]) -> dict:
    """p50 / p99 / max in ms of the loop's per-tick figures. ``timing``: arrays (N,) "start" (s,
    the tick starts) or "period", "late", "compute", optional "compute_cpu", "prewarm",
    "prewarm_calls", and per drone lists "infer", "obs"; ``names``: the drones, in that order."""
    period = np.asarray(timing["period"] if "period" in timing else periods(timing["start"]), dtype=np.float64)
    calls = timing.get("prewarm_calls", [])
    out = {"rate_hz": round(1.0 / dt, 3), "ticks": int(len(timing["compute"])),
           "late_ms": ms_stats(timing["late"]), "period_ms": ms_stats(period),
           "period_jitter_ms": ms_stats(np.abs(period - dt)),
           "compute_ms": ms_stats(timing["compute"]), "compute_cpu_ms": ms_stats(timing.get("compute_cpu", [])),
           "prewarm_ms": ms_stats(timing.get("prewarm", [])),
           "prewarm_calls_mean": round(float(np.mean(calls)), 2) if len(calls) else None,
           "inference_ms": {n: ms_stats(x) for n, x in zip(names, timing["infer"])},
           "observation_ms": {n: ms_stats(x) for n, x in zip(names, timing.get("obs", [[]] * len(names)))}}
    out["period_jitter_p99_ms"] = out["period_jitter_ms"]["p99"]
    out["compute_p99_ms"] = out["compute_ms"]["p99"]
    out["inference_p99_ms"] = max(((v["p99"] or 0.0) for v in out["inference_ms"].values()), default=0.0)
    return out


def _num(v) -> float:
    return float(v) if isinstance(v, (int, float)) and not isinstance(v, bool) else np.nan


def log_timing(data) -> tuple[dict, float, list[str], int] | None:
    """(timing arrays as loop_figures takes them, dt, drone names, skipped ticks) from a flight
    log's /timing messages, or None when it has none."""
    msgs = data.messages("/timing")
    if not msgs:
        return None
    bodies = data.meta.get("bodies")
    if not isinstance(bodies, list):
        bodies = sorted({b for _, m in msgs for b in (m.get("infer_s") or {})})
    names = [DRONE_NAMES[i] if i < len(DRONE_NAMES) else str(b) for i, b in enumerate(bodies)]
    rate = data.meta.get("rate_hz")
    dt = 1.0 / float(rate) if isinstance(rate, (int, float)) and rate > 0 else 0.01

    def col(key):
        return np.array([_num(m.get(key)) for _, m in msgs])

    def per_body(key):
        return [np.array([_num((m.get(key) or {}).get(b)) for _, m in msgs]) for b in bodies]

    timing = {"start": np.array([t for t, _ in msgs]), "late": col("late_s"), "compute": col("compute_s"),
              "compute_cpu": col("compute_cpu_s"), "prewarm": col("prewarm_s"),
              "prewarm_calls": np.array([m["prewarm_calls"] for _, m in msgs if isinstance(m.get("prewarm_calls"), int)]),
              "infer": per_body("infer_s"), "obs": per_body("obs_s")}
    skipped = int(np.nansum(col("skipped")))
    return timing, dt, names, skipped


def log_loop_figures(data) -> dict | None:
    """loop_figures of a flight log (plus "skipped"), or None when it has no /timing."""
    got = log_timing(data)
    if got is None:
        return None
    timing, dt, names, skipped = got
    return loop_figures(timing, dt, names) | {"skipped": skipped}
