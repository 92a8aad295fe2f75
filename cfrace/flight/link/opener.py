"""Links from URIs: the one place that picks a Link implementation for a drone's URI."""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Callable

from cfrace.errors import LinkError
from cfrace.flight.link.protocol import Link, RecordingLink

CFLIB_SCHEMES = ("radio://", "udp://", "usb://")


def open_link(uri: str, *, clock=time.monotonic) -> Link:
    """A Link for ``uri`` in this process: radio:// and udp:// go through cflib (crazyflie.py);
    null:// records only. sim://N (a drone of an in-process simulator) is made by
    cfrace.rehearsal.dryrun, which has it. Races hold their cflib links in the link keeper
    (``link_factory``); this in-process form is for tools and tests."""
    if uri.startswith(CFLIB_SCHEMES):
        from cfrace.flight.link.crazyflie import CflibLink

        return CflibLink(uri)
    if uri.startswith("sim://"):
        raise LinkError(f"{uri}: a sim:// link needs the in-process simulator (cfrace sim dry-run --lockstep)")
    if uri.startswith("null://"):
        return RecordingLink(uri, clock=clock)
    raise LinkError(f"{uri}: unknown link URI (expected radio://..., udp://HOST:PORT, sim://N, null://N)")


def check_link(link, uri: str) -> Link:
    """``link`` if it has every member of the Link protocol (cfrace/flight/link/protocol.py); else LinkError
    naming what it lacks, before anything is sent (a missing one would fail in the race)."""
    members = set(Link.__annotations__) | {m for m in vars(Link) if not m.startswith("_")}
    missing = sorted(m for m in members if not hasattr(link, m))
    if missing:
        raise LinkError(f"{uri}: {type(link).__name__} is not a cfrace Link: it lacks {', '.join(missing)} "
                        "(the Link protocol of cfrace/flight/link/protocol.py)")
    return link


def stop_log_path(log: Path | None) -> Path | None:
    """Where the link keeper records its stops: beside the flight log (FLIGHT.stops.jsonl)."""
    return None if log is None else Path(log).with_suffix(".stops.jsonl")


def link_factory(uris, *, heartbeat_s: float, stop_log: Path | None = None, rt_priority="auto", loop_cpu="off",
                 clock=time.monotonic, estop_watchdog: bool = False) -> Callable[[int, str], Link]:
    """open_link(i, uri) for a race: every cflib URI's link lives in ONE link keeper process
    (cfrace.flight.link.keeper: it stops every drone when the loop's process dies or goes silent for
    heartbeat_s), scheduled as the flight process's other threads (the CPUs other than the loop's,
    SCHED_FIFO one below the loop's where permitted: cfrace.flight.loop.realtime); other URIs as
    ``open_link``. ``estop_watchdog``: the keeper feeds each flying drone's emergency-stop watchdog."""
    from cfrace.flight.loop import realtime
    from cfrace.flight.link.keeper_client import LinkKeeper

    prio = realtime.resolve_rt_priority(rt_priority)
    keeper = LinkKeeper(uris, heartbeat_s=heartbeat_s, stop_log=stop_log, rt_priority=max(1, prio - 1) if prio else 0,
                        cpus=realtime.other_cpus(realtime.resolve_loop_cpu(loop_cpu)), estop_watchdog=estop_watchdog)

    def make(i: int, uri: str) -> Link:
        if uri.startswith(CFLIB_SCHEMES):
            if uri != keeper.uris[i]:
                raise LinkError(f"{uri}: not the URI the link keeper holds for drone {i}")
            return keeper.link(i)
        return open_link(uri, clock=clock)

    return make


def wait_heard(links, link_clock, limit_s: float, timeout_s: float = 2.0) -> None:
    """Until every live link has heard its drone within ``limit_s`` (LinkError after timeout_s): a
    link silent since before the start would be stopped at once by the first tick."""
    end = time.monotonic() + timeout_s
    while True:
        now = link_clock()
        silent = [k for k in links if not k.uri.startswith("null://") and not k.quality.rx_age(now) < limit_s]
        if not silent:
            return
        if time.monotonic() > end:
            age = silent[0].quality.rx_age(now)
            raise LinkError(f"{silent[0].uri}: the drone has " + (f"not answered for {age:.1f} s" if math.isfinite(age)
                                                                  else "never answered") + " before the start")
        time.sleep(0.01)
