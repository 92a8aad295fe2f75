"""cfrace.rehearsal.loop_timing.landing_tick_cpu (benchmarks/landing_ticks.py prints it): the CPU of each
landing tick of `cfrace bench loop`."""

from cfrace.rehearsal.loop_timing import landing_tick_cpu


def test_the_landing_ticks_of_a_four_drone_bench_are_reported():
    doc = landing_tick_cpu(drones=4, track="complex", duration_s=1.0)
    ticks = {k: n for _, k, n in doc["landing_ticks_cpu_ms"]}
    first = min(ticks)
    assert ticks[first] == 4 and len(ticks) > 10     # every drone starts landing in the same tick
    assert all(ms >= 0.0 for ms, _, _ in doc["landing_ticks_cpu_ms"])
    assert doc["racing_cpu_ms"]["p50"] > 0.0 and doc["drones"] == 4
