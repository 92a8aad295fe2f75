"""Scheduling of the flight loop: SCHED_FIFO and a CPU of its own for the loop thread."""

from __future__ import annotations

import os
import re
import threading

import pytest

from cfrace.errors import ConfigError
from cfrace.flight.loop import realtime
from cfrace.flight.config import FlightConfig, load_flight_file

needs_two_cpus = pytest.mark.skipif(not hasattr(os, "sched_setaffinity") or len(os.sched_getaffinity(0)) < 2,
                                    reason="pinning needs Linux and two or more CPUs")


def test_rt_priority_is_set_for_every_thread_and_restored():
    stop = threading.Event()
    helper = threading.Thread(target=stop.wait, daemon=True)
    helper.start()
    before = os.sched_getscheduler(0)
    changed = realtime.set_fifo(20)
    try:
        if changed is None:
            pytest.skip("no permission for SCHED_FIFO here")
        assert os.sched_getscheduler(0) == os.SCHED_FIFO and os.sched_getparam(0).sched_priority == 20
        assert os.sched_getscheduler(helper.native_id) == os.SCHED_FIFO
        assert os.sched_getparam(helper.native_id).sched_priority == 19
    finally:
        realtime.restore_scheduler(changed)
        stop.set()
    assert os.sched_getscheduler(0) == before
    assert realtime.set_fifo(0) is None


@pytest.mark.parametrize("value, want", [("auto", "auto"), ("OFF", "off"), (" 1 ", 1), (0, 0), ("3", 3)])
def test_loop_cpu_setting_parses(value, want):
    assert realtime.parse_loop_cpu(value) == want
    assert FlightConfig(track="lemniscate", ego="ds", opp="ds", loop_cpu=value).loop_cpu == want


@pytest.mark.parametrize("value", ["fast", "-1", -1, 1.5, True, ""])
def test_a_bad_loop_cpu_is_one_clear_error(value):
    with pytest.raises(ConfigError, match="loop_cpu: "):
        FlightConfig(track="lemniscate", ego="ds", opp="ds", loop_cpu=value)


def test_loop_cpu_in_a_flight_config_file(tmp_path):
    f = tmp_path / "room.yaml"
    f.write_text("loop_cpu: 1\n")
    assert load_flight_file(f)["loop_cpu"] == 1
    f.write_text("loop_cpu: fastest\n")
    with pytest.raises(ConfigError) as exc:
        load_flight_file(f)
    assert str(exc.value) == f"{f}: key 'loop_cpu': expected auto, off or a CPU number, got 'fastest'"


def test_resolve_loop_cpu_on_this_machine():
    cpus = realtime.allowed_cpus()
    assert realtime.resolve_loop_cpu("off") is None
    if not hasattr(os, "sched_setaffinity"):
        assert realtime.resolve_loop_cpu("auto") is None
        return
    assert realtime.resolve_loop_cpu("auto") == (max(cpus) if len(cpus) >= 2 else None)
    missing = max(cpus) + 1
    with pytest.raises(ConfigError, match=f"loop_cpu: CPU {missing} is not available to this process"):
        realtime.resolve_loop_cpu(missing)


@needs_two_cpus
def test_pinning_gives_the_loop_thread_its_cpu_and_moves_every_other_thread_off_it():
    stop = threading.Event()
    helper = threading.Thread(target=stop.wait, daemon=True)
    helper.start()
    before = os.sched_getaffinity(0)
    cpu = realtime.resolve_loop_cpu("auto")
    changed = realtime.pin_loop_thread(cpu)
    try:
        assert os.sched_getaffinity(0) == {cpu}
        assert os.sched_getaffinity(helper.native_id) == before - {cpu}
        later = threading.Thread(target=stop.wait, daemon=True)   # started by the loop thread: inherits its CPU
        later.start()
        assert os.sched_getaffinity(later.native_id) == {cpu}
    finally:
        realtime.restore_affinity(changed)
        stop.set()
    assert os.sched_getaffinity(0) == before and os.sched_getaffinity(helper.native_id) == before
    assert realtime.pin_loop_thread(None) is None
    assert realtime.pin_loop_thread(4095) is None and os.sched_getaffinity(0) == before   # refused: unpinned


@pytest.mark.parametrize("value, want", [("auto", "auto"), (" AUTO", "auto"), (0, 0), ("50", 50), (99, 99)])
def test_rt_priority_setting_parses(value, want):
    assert realtime.parse_rt_priority(value) == want
    assert FlightConfig(track="lemniscate", ego="ds", opp="ds", rt_priority=value).rt_priority == want
    assert realtime.resolve_rt_priority(value) == (realtime.AUTO_RT_PRIORITY if want == "auto" else want)


@pytest.mark.parametrize("value, problem", [(100, "must be in [0, 99], got 100"), ("-1", "expected auto or a priority 0-99"),
                                            ("high", "expected auto or a priority 0-99"), (True, "expected auto")])
def test_a_bad_rt_priority_is_one_clear_error(value, problem, tmp_path):
    with pytest.raises(ConfigError, match=f"rt_priority: {re.escape(problem)}"):
        FlightConfig(track="lemniscate", ego="ds", opp="ds", rt_priority=value)
    f = tmp_path / "room.yaml"
    f.write_text(f"rt_priority: {str(value).lower()}\n")
    with pytest.raises(ConfigError, match=f"^{re.escape(str(f))}: key 'rt_priority': "):
        load_flight_file(f)


def fifo_permitted() -> bool:
    """Whether this process may run a thread SCHED_FIFO (tried on a helper thread, then undone)."""
    res = []

    def probe():
        try:
            os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(1))
            res.append(True)
        except (OSError, AttributeError):
            res.append(False)

    t = threading.Thread(target=probe)
    t.start()
    t.join()
    return res[0]


def test_the_pre_flight_summary_names_the_loop_cpu_and_priority():
    import io
    from dataclasses import asdict

    from rich.console import Console

    from cfrace.cli.flight import announce
    from cfrace.flight.config import SafetyConfig
    from cfrace.flight.safety.check import Fence
    from cfrace.track import load_track

    def text(**kw):
        buf = io.StringIO()
        meta = {"policies": {"ego": {"method": "ours", "path": "a.onnx", "obs_layout": "race42"},
                             "opp": {"method": "ds", "path": "b.onnx", "obs_layout": "solo36"}},
                "uris": ["udp://127.0.0.1:1", "udp://127.0.0.1:2"], "bodies": ["cf1", "cf2"],
                "fence": Fence.from_track(load_track("lemniscate"), 0.3), "safety": asdict(SafetyConfig()),
                "latency_comp_s": 0.01, "laps": 3, "track": "lemniscate", **kw}
        announce(meta, Console(file=buf, width=400))
        return " ".join(buf.getvalue().split())

    assert "loop thread on CPU 1, the rest elsewhere, SCHED_FIFO 50 where permitted;" in text(loop_cpu=1, rt_priority=50)
    assert "loop thread not pinned; 3 laps" in text(loop_cpu=None, rt_priority=0)
