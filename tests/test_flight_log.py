"""Flight log: real MCAP files on disk, killed writers, cut files, garbage, the `cfrace log` CLI."""

from __future__ import annotations

import json
import math
import os
import signal
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from cfrace.errors import LogError
from cfrace.flight.log.writer import FlightLog, read_log

CFRACE = Path(sys.executable).parent / "cfrace"
PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def make_log(path: Path, ticks: int = 200, close: bool = True) -> Path:
    """A small two-drone flight over the complex track: every topic the loop writes."""
    log = FlightLog(path, {"track": "complex", "obstacles": False, "bodies": ["cf1", "cf2"],
                           "mocap": "sim", "period_s": 0.01})
    for k in range(ticks):
        t = 0.01 * k
        pos = {"cf1": np.array([1.5 - t, 3.5, 0.75]), "cf2": np.array([1.5, 3.5 - 2 * t, 1.0])}
        log.write("/mocap/pose", t, {"t_src": 100 + t, "seq": k + 1,
                                     "poses": {b: {"pos": p, "quat": [1.0, 0, 0, 0]} for b, p in pos.items()}})
        log.write("/estimate", t, {b: {"pos": p, "vel": np.array([-1.0, 0, 0]) if b == "cf1" else
                                       np.array([0, -2.0, 0]), "quat": np.array([1.0, 0, 0, 0]),
                                       "age_s": 0.0, "valid": True} for b, p in pos.items()})
        log.write("/timing", t, {"period_s": 0.01 + 1e-4 * (k % 7), "compute_s": 0.002, "i": k})
    log.write("/safety", 1.0, {"kind": "geofence", "drone": 1, "action": "stop_drone", "detail": "x out"})
    log.write("/race", 2.0, {"cf1": {"gates_passed": 1, "laps": 0}, "cf2": {"gates_passed": 0}})
    if close:
        log.close({"race": {"winner": "cf1"}})
    return path


def test_round_trip(tmp_path):
    path = tmp_path / "flight.mcap"
    log = FlightLog(path, {"track": "complex", "uris": ["udp://127.0.0.1:19850"]})
    log.write("/estimate", 0.5, {"cf1": {"pos": np.array([1.0, 2.0, 3.0]), "age_s": math.nan,
                                         "n": np.int64(7)}, "t": 99.0})
    log.write("/event", 0.75, {"kind": "start", "text": "go", "set": {3, 1}})
    log.close({"race": {"winner": "cf1"}})
    log.close({"ignored": True})          # idempotent
    log.write("/event", 1.0, {"late": True})   # dropped after close, no error

    data = read_log(path)
    assert data.complete and not data.truncated and data.stop_reason == ""
    assert data.meta["track"] == "complex" and data.meta["uris"] == ["udp://127.0.0.1:19850"]
    assert data.meta["cfrace_version"] and data.meta["start_time"] and "command" in data.meta
    assert data.topics == ["/meta", "/estimate", "/event", "/summary"]
    (t, msg), = data.messages("/estimate")
    assert t == 0.5 and msg["t_msg"] == 99.0
    assert msg["cf1"] == {"pos": [1.0, 2.0, 3.0], "age_s": None, "n": 7}
    assert data.messages("/event")[0][1]["set"] == [1, 3]
    assert data.summary["race"] == {"winner": "cf1"} and data.summary["clean"] is True
    assert "ignored" not in data.summary
    assert data.summary["messages"] == {"/meta": 1, "/estimate": 1, "/event": 1}
    assert data.summary["duration_s"] == pytest.approx(0.25)


def test_standard_mcap_readers_accept_the_file(tmp_path):
    """Not only our lenient reader: mcap's indexed reader sees the channels, schemas and stats."""
    from mcap.reader import make_reader
    path = make_log(tmp_path / "f.mcap", ticks=20)
    with open(path, "rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        topics = {c.topic: c for c in summary.channels.values()}
        assert topics["/timing"].message_encoding == "json"
        schema = summary.schemas[topics["/timing"].schema_id]
        assert schema.encoding == "jsonschema" and json.loads(schema.data)["title"] == "/timing"
        assert summary.statistics.message_count == 1 + 3 * 20 + 3
        n = sum(1 for _ in reader.iter_messages(topics=["/estimate"]))
    assert n == 20


_KILLED_WRITER = textwrap.dedent("""
    import sys, numpy as np
    from cfrace.flight.log.writer import FlightLog
    log = FlightLog(sys.argv[1], {"track": "complex"})
    i = 0
    while True:
        log.write("/timing", 0.01 * i, {"i": i, "period_s": 0.01, "pad": np.arange(20.0)})
        i += 1
        if i % 50 == 0:
            print(i, flush=True)
""")


def test_sigkill_mid_flight_leaves_a_readable_log(tmp_path):
    path = tmp_path / "killed.mcap"
    proc = subprocess.Popen([sys.executable, "-c", _KILLED_WRITER, str(path)], stdout=subprocess.PIPE,
                            text=True)
    try:
        written = 0
        while written < 1000:
            line = proc.stdout.readline()
            assert line, "writer died early"
            written = int(line)
    finally:
        proc.send_signal(signal.SIGKILL)
        proc.wait(5)
    assert proc.returncode == -signal.SIGKILL
    data = read_log(path)
    assert data.truncated and not data.complete and data.summary is None
    assert data.meta["track"] == "complex"
    ids = [m["i"] for _, m in data.messages("/timing")]
    assert len(ids) >= written                      # nothing acknowledged was lost
    assert ids == list(range(len(ids)))             # in order, no gap, no damaged message
    assert data.bad_messages == 0


def test_bytes_cut_off_at_the_end(tmp_path):
    full = make_log(tmp_path / "full.mcap", ticks=100)
    raw = full.read_bytes()
    total = len(read_log(full).messages("/timing"))
    cut = tmp_path / "cut.mcap"
    last_count = total
    # from "one byte missing" down to half the file: never an exception, always a prefix
    for size in sorted({len(raw) - 1, len(raw) - 9, len(raw) - 100, *range(len(raw) - 1, len(raw) // 2, -997)},
                       reverse=True):
        cut.write_bytes(raw[:size])
        data = read_log(cut)
        assert data.truncated and not data.complete, size
        ids = [m["i"] for _, m in data.messages("/timing")]
        assert ids == list(range(len(ids))) and len(ids) <= last_count
        last_count = len(ids)
    assert last_count < total
    cut.write_bytes(raw[:len(raw) - 1])      # only the closing magic is damaged: all data is there
    data = read_log(cut)
    assert data.summary is not None and len(data.messages("/timing")) == total


@pytest.mark.parametrize("content", [b"", b"hello", b"not an mcap file at all\n" * 50, bytes(range(256)) * 4])
def test_garbage_is_a_one_line_log_error(tmp_path, content):
    path = tmp_path / "garbage.mcap"
    path.write_bytes(content)
    with pytest.raises(LogError) as err:
        read_log(path)
    assert str(path) in str(err.value) and "\n" not in str(err.value)


def test_missing_file_and_mcap_without_meta(tmp_path):
    with pytest.raises(LogError, match="cannot read flight log"):
        read_log(tmp_path / "nope.mcap")
    from mcap.writer import Writer
    other = tmp_path / "other.mcap"
    with open(other, "wb") as f:
        w = Writer(f)
        w.start()
        ch = w.register_channel("/foo", "json", 0)
        w.add_message(ch, 0, b"{}", 0)
        w.finish()
    with pytest.raises(LogError, match="no /meta"):
        read_log(other)
    # the first bytes of a real log: magic + header, cut before /meta
    head = make_log(tmp_path / "h.mcap", ticks=1).read_bytes()[:30]
    other.write_bytes(head)
    with pytest.raises(LogError):
        read_log(other)


def test_close_from_a_signal_handler_interrupting_writes(tmp_path):
    path = tmp_path / "sig.mcap"
    log = FlightLog(path, {"track": "complex"})
    calls = []

    def handler(signum, frame):
        calls.append(log._owner is not None)   # whether it landed inside write()'s lock
        log.close({"stopped_by": "SIGALRM"})

    old = signal.signal(signal.SIGALRM, handler)
    try:
        signal.setitimer(signal.ITIMER_REAL, 0.05)
        i, deadline = 0, time.monotonic() + 10
        while not log.closed and time.monotonic() < deadline:
            log.write("/timing", 0.01 * i, {"i": i, "pad": list(range(50))})
            i += 1
    finally:
        signal.setitimer(signal.ITIMER_REAL, 0)
        signal.signal(signal.SIGALRM, old)
    assert calls and log.closed
    data = read_log(path)
    assert data.complete and data.summary["stopped_by"] == "SIGALRM"
    ids = [m["i"] for _, m in data.messages("/timing")]
    assert ids == list(range(len(ids))) and len(ids) in (i - 1, i)   # the interrupted write may be dropped


class _SignalOnFlush:
    """File proxy that raises a real signal inside FlightLog.write's locked region."""

    def __init__(self, f, at: int):
        self._f, self._n, self._at = f, 0, at

    def flush(self):
        self._f.flush()
        self._n += 1
        if self._n == self._at:
            signal.raise_signal(signal.SIGUSR1)   # the handler runs before flush() returns to write()

    def __getattr__(self, name):
        return getattr(self._f, name)


def test_close_from_a_signal_handler_inside_a_write_is_deferred(tmp_path):
    path = tmp_path / "sig2.mcap"
    log = FlightLog(path, {"track": "complex"})
    seen = []

    def handler(signum, frame):
        seen.append(log._owner)
        log.close({"stopped_by": "SIGUSR1"})      # must neither deadlock nor corrupt the record
        seen.append(log.closed)

    old = signal.signal(signal.SIGUSR1, handler)
    log._file = _SignalOnFlush(log._file, at=5)
    try:
        for i in range(10):
            log.write("/timing", 0.01 * i, {"i": i})
    finally:
        signal.signal(signal.SIGUSR1, old)
    assert seen[0] is not None and seen[1] is False   # it landed inside write(): close deferred
    assert log.closed                                 # ... and done when that write finished
    data = read_log(path)
    assert data.complete and data.summary["stopped_by"] == "SIGUSR1"
    assert [m["i"] for _, m in data.messages("/timing")] == [0, 1, 2, 3, 4]   # the 5th write completed


def test_concurrent_writers(tmp_path):
    path = tmp_path / "threads.mcap"
    log = FlightLog(path, {"track": "complex"})

    def worker(k):
        for j in range(300):
            log.write(f"/w{k}", j * 0.01, {"k": k, "j": j, "v": np.full(5, j)})

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for th in threads:
        th.start()
    for th in threads:
        th.join()
    log.close()
    data = read_log(path)
    assert data.complete and data.bad_messages == 0
    for k in range(4):
        assert [m["j"] for _, m in data.messages(f"/w{k}")] == list(range(300))


def test_disk_errors_do_not_stop_the_flight(tmp_path):
    blocker = tmp_path / "blocker"
    blocker.write_text("a file where a directory should be")
    with pytest.raises(LogError, match="cannot write flight log"):
        FlightLog(blocker / "x.mcap", {})
    if os.path.exists("/dev/full"):
        log = FlightLog("/dev/full", {"track": "complex"})   # every write fails with ENOSPC
        log.write("/timing", 0.0, {"i": 0})
        log.close()
        assert log.error is not None and log.closed


def test_log_info_cli(tmp_path):
    good = make_log(tmp_path / "good.mcap")
    out = subprocess.run([str(CFRACE), "log", "info", str(good)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    for text in ("closed cleanly", "/estimate", "geofence", "winner", "p99", "complex"):
        assert text in out.stdout, text

    raw = good.read_bytes()
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(raw[: len(raw) * 2 // 3])
    out = subprocess.run([str(CFRACE), "log", "info", str(cut)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0, out.stderr
    assert "truncated" in out.stdout and "/timing" in out.stdout

    garbage = tmp_path / "garbage.mcap"
    garbage.write_bytes(b"this is not a flight log\n" * 10)
    out = subprocess.run([str(CFRACE), "log", "info", str(garbage)], capture_output=True, text=True, timeout=60)
    assert out.returncode == 2
    assert out.stderr.startswith("error: ") and out.stderr.count("\n") == 1
    assert "Traceback" not in out.stderr + out.stdout and str(garbage) in out.stderr


def test_log_plot_writes_pngs(tmp_path):
    import matplotlib.image as mpimg
    from cfrace.flight.log.plots import log_stats, plot_log

    path = make_log(tmp_path / "p.mcap")
    data = read_log(path)
    stats = log_stats(data)
    assert stats.loop["period_ms"]["p50"] == pytest.approx(10.0, abs=0.01)   # tick starts 10 ms apart
    assert stats.loop["compute_ms"]["max"] == pytest.approx(2.0)
    assert [(e.kind, e.who) for e in stats.safety] == [("geofence", "1")]
    assert stats.race == {"winner": "cf1"} and stats.bodies == ["cf1", "cf2"]

    out = subprocess.run([str(CFRACE), "log", "plot", str(path), "-o", str(tmp_path / "png")],
                         capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    pngs = sorted((tmp_path / "png").glob("*.png"))
    assert [p.name for p in pngs] == ["p_speed.png", "p_timing.png", "p_trajectory.png"]
    for p in pngs:
        assert p.read_bytes()[:8] == PNG_MAGIC
        img = mpimg.imread(p)
        assert img.shape[0] > 300 and img.shape[1] > 300 and img.std() > 0.01   # not blank
    # a log without estimates still plots its mocap trajectory (velocity by differences)
    bare = FlightLog(tmp_path / "bare.mcap", {"track": "lemniscate"})
    for k in range(50):
        bare.write("/mocap/pose", k * 0.01, {"t_src": k * 0.01, "seq": k,
                                             "poses": {"cf1": {"pos": [0.02 * k, 4.0, 1.0], "quat": [1, 0, 0, 0]}}})
    bare.close()
    written = plot_log(read_log(tmp_path / "bare.mcap"), tmp_path / "png2")
    assert [p.name for p in written] == ["bare_trajectory.png", "bare_speed.png"]
