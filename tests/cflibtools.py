"""Helpers for tests that drive simulated Crazyflies with the real cflib client."""

import time
from contextlib import contextmanager

from cflib.crazyflie import Crazyflie
from cflib.crazyflie.syncCrazyflie import SyncCrazyflie


def connect(uri):
    """A SyncCrazyflie without a TOC cache (every test reads the TOCs over the wire)."""
    return SyncCrazyflie(uri, cf=Crazyflie(rw_cache=None))


def wait_for(cond, timeout=2.0):
    """Poll cond() every 10 ms until it is true or timeout s pass; its last value."""
    t_end = time.monotonic() + timeout
    while time.monotonic() < t_end:
        if cond():
            return True
        time.sleep(0.01)
    return cond()


@contextmanager
def served(fleet, index=0):
    """fleet served over UDP and cflib connected to drone index, its parameters read: -> the Crazyflie."""
    from cfrace.simcf.server import SimCrazyflieServer
    with SimCrazyflieServer(fleet, base_port=0) as server, connect(server.uris[index]) as scf:
        scf.wait_for_params()
        yield scf.cf
