"""What one UDP send on 127.0.0.1 costs the flight loop: back to back, once every 10 ms, and once
every 10 ms after the path was warmed.

    python studies/flight_timing/udp_cold.py [--sends 400] [--cpu N]

The loop sends each drone one setpoint datagram per tick (udp:// links: the simulated drones).
Measured is the sending thread's CPU time for socket.send of a 16-byte datagram to a socket in
this process, in six ways: back to back; every 10 ms with a sleep in between; every 10 ms after a
3-ms window of warm datagrams to a second socket of our own; after one warm datagram 3 ms before;
after one warm datagram 0.2 ms before, in a busy wait; and the busy wait without datagrams. (The
loop itself no longer sends on a socket: its setpoints go through a pipe to the link keeper,
cfrace/flight/link/keeper.py.) Pinned to one CPU (--cpu, default
the highest). p50 / p90 / p99 in us. Used for docs/benchmarks.md ("Loop CPU and priority").
"""

from __future__ import annotations

import argparse
import os
import socket
import time

import numpy as np

DATAGRAM = bytes(16)


def _pair() -> tuple[socket.socket, socket.socket]:
    rx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    rx.bind(("127.0.0.1", 0))
    rx.setblocking(False)
    tx = socket.socket(socket.AF_INET, socket.SOCK_DGRAM)
    tx.connect(rx.getsockname())
    return rx, tx


def _drain(sock: socket.socket) -> None:
    try:
        while True:
            sock.recv(64)
    except BlockingIOError:
        pass


def measure(mode: str, sends: int) -> np.ndarray:
    dst_rx, dst_tx = _pair()
    warm_rx, warm_tx = _pair()
    out = []
    for _ in range(sends):
        if mode == "every 10 ms":
            time.sleep(0.010)
        elif mode != "back to back":
            deadline = time.perf_counter() + 0.010
            time.sleep(0.007)
            if mode == "warm window":
                while time.perf_counter() < deadline - 1e-4:
                    warm_tx.send(DATAGRAM)
                    warm_rx.recv(64)
            elif mode == "one warm datagram":
                warm_tx.send(DATAGRAM)
                warm_rx.recv(64)
            elif mode == "one warm 0.2 ms before":
                while time.perf_counter() < deadline - 2e-4:
                    pass
                warm_tx.send(DATAGRAM)
                warm_rx.recv(64)
            while time.perf_counter() < deadline:
                pass
        c = time.thread_time()
        dst_tx.send(DATAGRAM)
        out.append(time.thread_time() - c)
        _drain(dst_rx)
    for s in (dst_rx, dst_tx, warm_rx, warm_tx):
        s.close()
    return np.asarray(out) * 1e6


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sends", type=int, default=400)
    ap.add_argument("--cpu", type=int, default=None)
    args = ap.parse_args()
    if hasattr(os, "sched_setaffinity"):
        cpu = max(os.sched_getaffinity(0)) if args.cpu is None else args.cpu
        os.sched_setaffinity(0, {cpu})
    print(f"{time.strftime('%Y-%m-%d %H:%M:%S')}, load average {os.getloadavg()[0]:.2f}; "
          f"CPU time of one socket.send, us")
    for mode in ("back to back", "every 10 ms", "warm window", "one warm datagram", "one warm 0.2 ms before",
                 "busy wait only"):
        x = measure(mode, args.sends)
        print(f"{mode:>22s}: p50 {np.median(x):6.1f}  p90 {np.percentile(x, 90):6.1f}  p99 {np.percentile(x, 99):6.1f}")


if __name__ == "__main__":
    main()
