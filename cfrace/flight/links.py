"""Links from URIs: the one place that picks a Link implementation for a drone's URI."""

from __future__ import annotations

import time

from cfrace.errors import LinkError
from cfrace.flight.link import DirectSimLink, Link, RecordingLink


def open_link(uri: str, *, fleet=None, clock=time.monotonic) -> Link:
    """A Link for ``uri``: radio:// and udp:// go through cflib (link_cflib.py); sim://N is a
    DirectSimLink to drone N of ``fleet``; null:// records only."""
    if uri.startswith(("radio://", "udp://", "usb://")):
        from cfrace.flight.link_cflib import CflibLink

        return CflibLink(uri)
    if uri.startswith("sim://"):
        if fleet is None:
            raise LinkError(f"{uri}: a sim:// link needs the in-process simulator (cfrace sim dry-run --lockstep)")
        try:
            index = int(uri[len("sim://"):])
        except ValueError:
            raise LinkError(f"{uri}: expected sim://INDEX") from None
        return DirectSimLink(fleet, index, clock=clock)
    if uri.startswith("null://"):
        return RecordingLink(uri, clock=clock)
    raise LinkError(f"{uri}: unknown link URI (expected radio://..., udp://HOST:PORT, sim://N)")
