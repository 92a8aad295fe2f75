"""Links from URIs: the one place that picks a Link implementation for a drone's URI."""

from __future__ import annotations

import time

from cfrace.errors import LinkError
from cfrace.flight.link import Link, RecordingLink


def open_link(uri: str, *, clock=time.monotonic) -> Link:
    """A Link for ``uri``: radio:// and udp:// go through cflib (link_cflib.py); null:// records
    only. sim://N (a drone of an in-process simulator) is made by cfrace.flight.dryrun, which has it."""
    if uri.startswith(("radio://", "udp://", "usb://")):
        from cfrace.flight.link_cflib import CflibLink

        return CflibLink(uri)
    if uri.startswith("sim://"):
        raise LinkError(f"{uri}: a sim:// link needs the in-process simulator (cfrace sim dry-run --lockstep)")
    if uri.startswith("null://"):
        return RecordingLink(uri, clock=clock)
    raise LinkError(f"{uri}: unknown link URI (expected radio://..., udp://HOST:PORT, sim://N)")
