"""Scheduling of the flight loop: SCHED_FIFO and a CPU of its own for the loop thread."""

from __future__ import annotations

import os
import threading

import pytest

from cfrace.errors import ConfigError
from cfrace.flight import realtime
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
