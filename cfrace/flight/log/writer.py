"""The flight log: one MCAP file per flight, JSON messages with JSON schemas, plus the Foxglove
scene's messages in the SDK's schemas (cfrace.flight.log.foxglove_scene; Foxglove opens it).

Written as the drones fly: every message goes through to the operating system at once (unchunked
MCAP records, file flushed per message, fsync'd by a background thread about once a second), so a
killed process or a power cut leaves a file that `read_log` reads up to the cut. `close(summary)`
writes /summary and the MCAP summary section and footer; it is idempotent, thread-safe and may be
called from a signal handler (even one that interrupted `write`). Topics: docs/flight-log.md.
Every stored message is the caller's dict plus "t" (s, the flight clock given to `write`); a key
"t" in the caller's dict is stored as "t_msg". numpy arrays become lists, NaN/inf become null.
The MCAP log_time is wall-clock ns (start time + monotonic elapsed), so Foxglove shows real dates.
"""

from __future__ import annotations

import json
import math
import os
import sys
import threading
import time
from collections import Counter
from datetime import datetime, timezone
from pathlib import Path
from typing import Any

import numpy as np
from mcap.writer import CompressionType, Writer

import cfrace
from cfrace.errors import LogError
from cfrace.flight.log.reader import FlightLogData, read_log

__all__ = ["FlightLog", "FlightLogData", "read_log", "encode", "TOPICS", "PROFILE"]

PROFILE = "cfrace-flight"   #: MCAP header profile
_OBJ = {"type": "object"}
_VEC3 = {"type": "array", "items": {"type": ["number", "null"]}, "minItems": 3, "maxItems": 3}
_QUAT = {"type": "array", "items": {"type": ["number", "null"]}, "minItems": 4, "maxItems": 4,
         "description": "quaternion w, x, y, z (world from body)"}
_PER_BODY = "object keyed by mocap body name"

#: topic -> (description, JSON schema of its message without the common "t" field)
TOPICS: dict[str, tuple[str, dict]] = {
    "/meta": ("flight set-up, written first", _OBJ),
    "/mocap/pose": ("one motion-capture frame as received", {
        "type": "object", "properties": {
            "t_src": {"type": "number", "description": "s, mocap source clock"},
            "seq": {"type": "integer"},
            "poses": {"type": "object", "description": _PER_BODY, "additionalProperties": {
                "type": "object", "properties": {"pos": _VEC3, "quat": _QUAT}}}}}),
    "/estimate": ("state estimate per body", {
        "type": "object", "description": _PER_BODY, "additionalProperties": {
            "type": "object", "properties": {
                "pos": _VEC3, "vel": _VEC3, "quat": _QUAT, "age_s": {"type": ["number", "null"]},
                "valid": {"type": "boolean"}}}}),
    "/obs": ("policy observation per body (the training layout)", _OBJ),
    "/action": ("policy action per body, 4 values in [-1, 1]", _OBJ),
    "/setpoint": ("command sent per body (SI and link units)", _OBJ),
    "/safety": ("a safety check that tripped, or the per-tick safety state", _OBJ),
    "/timing": ("loop timing, one per tick: period_s, compute_s, ...", _OBJ),
    "/race": ("race progress per body: gates_passed, laps, target, crashed", _OBJ),
    "/link": ("radio link state per body", _OBJ),
    "/event": ("free-form events: kind, text", _OBJ),
    "/summary": ("written by close(): clean end, duration, counts and the caller's summary", _OBJ),
}


def _jsonable(obj: Any) -> Any:
    """json.dumps default: numpy, paths, sets, anything else as its str."""
    if isinstance(obj, np.ndarray):
        return obj.tolist()
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (set, frozenset)):
        return sorted(obj, key=str)
    if isinstance(obj, (tuple, list)):
        return list(obj)
    return str(obj)


def _finite(obj: Any) -> Any:
    """A copy with non-finite floats replaced by None (JSON has no NaN)."""
    if isinstance(obj, float):
        return obj if math.isfinite(obj) else None
    if isinstance(obj, dict):
        return {str(k): _finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple, set, frozenset, np.ndarray, np.generic)):
        obj = _jsonable(obj)
        return [_finite(v) for v in obj] if isinstance(obj, list) else _finite(obj)
    return obj


def encode(msg: dict) -> bytes:
    """dict -> compact JSON bytes (numpy to lists, NaN/inf to null)."""
    try:
        text = json.dumps(msg, default=_jsonable, allow_nan=False, separators=(",", ":"))
    except ValueError:   # a NaN or inf somewhere
        text = json.dumps(_finite(msg), default=_jsonable, allow_nan=False, separators=(",", ":"))
    return text.encode()


class FlightLog:
    """An MCAP flight log written as it flies. write() never raises on disk errors (the flight
    must go on): the first OSError is kept in .error and later writes are dropped."""

    def __init__(self, path: str | Path, meta: dict, *, fsync_interval_s: float | None = 1.0):
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._file = open(self.path, "wb")
        except OSError as exc:
            raise LogError(f"cannot write flight log {self.path}: {exc.strerror or exc}") from None
        self._lock = threading.Lock()
        self._owner: int | None = None          # thread id holding the lock inside write()
        self._pending: dict | None = None       # close() requested while write() was running
        self._closed = False
        self.error: OSError | None = None
        self.counts: Counter[str] = Counter()
        self._channels: dict[str, int] = {}
        self._schemas: dict[tuple, int] = {}
        self._t_first: float | None = None
        self._t_last: float | None = None
        self._wall0_ns, self._mono0_ns = time.time_ns(), time.monotonic_ns()
        self._dirty = threading.Event()         # written since the last fsync
        self._stop_sync = threading.Event()
        self._writer = Writer(self._file, use_chunking=False, compression=CompressionType.NONE)
        self._writer.start(profile=PROFILE, library=f"cfrace {cfrace.__version__}")
        now = datetime.now(timezone.utc)
        full = {"cfrace_version": cfrace.__version__, "start_time": now.isoformat(),
                "start_time_unix_s": now.timestamp(), "command": " ".join(sys.argv),
                "pid": os.getpid(), **meta}
        self.write("/meta", 0.0, full)
        if fsync_interval_s:
            threading.Thread(target=self._sync_loop, args=(fsync_interval_s,), daemon=True,
                             name="flightlog-fsync").start()

    # -- writing -------------------------------------------------------------------------------
    def write(self, topic: str, t: float, msg: dict) -> None:
        """Append one message on `topic` at flight time t (s); thread-safe, flushed at once."""
        if self._closed or self.error is not None:
            return
        payload = {"t": float(t)}
        for key, value in msg.items():
            payload["t_msg" if key == "t" else key] = value
        self._locked_append(topic, float(t), encode(payload))

    def write_encoded(self, topic: str, t: float, data: bytes, schema: tuple[str, str, bytes],
                      message_encoding: str) -> None:
        """Append one message encoded by the caller (the Foxglove scene: cfrace.flight.log.foxglove_scene)
        on `topic`, whose channel gets ``schema`` = (name, encoding, data) and ``message_encoding``
        when it first appears. Same guarantees as write()."""
        if not (self._closed or self.error is not None):
            self._locked_append(topic, float(t), data, (*schema, message_encoding))

    def _locked_append(self, topic: str, t: float, data: bytes, channel: tuple | None = None) -> None:
        with self._lock:
            self._owner = threading.get_ident()
            try:
                if not self._closed:
                    if channel is not None and topic not in self._channels:
                        self._register_schema(topic, *channel)
                    self._append(topic, t, data)
            finally:
                self._owner = None
        if self._pending is not None:          # a signal handler asked to close meanwhile
            self.close(self._pending)

    def _append(self, topic: str, t: float, data: bytes) -> None:
        try:
            channel = self._channels.get(topic)
            if channel is None:
                channel = self._register(topic)
            log_ns = self._wall0_ns + time.monotonic_ns() - self._mono0_ns
            self._writer.add_message(channel, log_time=log_ns, data=data, publish_time=log_ns,
                                     sequence=self.counts[topic])
            self._file.flush()
        except OSError as exc:
            self.error = exc
            return
        self.counts[topic] += 1
        if topic not in ("/meta", "/summary"):
            self._t_first = t if self._t_first is None else min(self._t_first, t)
            self._t_last = t if self._t_last is None else max(self._t_last, t)
        self._dirty.set()

    def _register(self, topic: str) -> int:
        description, schema = TOPICS.get(topic, ("", _OBJ))
        full = dict(schema)
        props = dict(full.get("properties", {}))
        props["t"] = {"type": "number", "description": "s, flight clock"}
        full.update(title=topic, description=description, properties=props)
        return self._register_schema(topic, topic.strip("/").replace("/", "."), "jsonschema",
                                     json.dumps(full).encode(), "json")

    def _register_schema(self, topic: str, name: str, encoding: str, data: bytes, message_encoding: str) -> int:
        """The schema (once per name) and the channel of `topic`."""
        key = (name, encoding, data)
        schema_id = self._schemas.get(key)
        if schema_id is None:
            schema_id = self._schemas[key] = self._writer.register_schema(name=name, encoding=encoding, data=data)
        self._channels[topic] = self._writer.register_channel(topic=topic, message_encoding=message_encoding,
                                                              schema_id=schema_id)
        return self._channels[topic]

    def _sync_loop(self, interval: float) -> None:
        while not self._stop_sync.wait(interval):
            if self._dirty.is_set():
                self._dirty.clear()
                try:
                    os.fsync(self._file.fileno())
                except (OSError, ValueError):
                    return

    # -- closing -------------------------------------------------------------------------------
    @property
    def closed(self) -> bool:
        return self._closed

    def close(self, summary: dict | None = None) -> None:
        """Write /summary and finish the file. Idempotent; safe from finally blocks, other threads
        and signal handlers (if it interrupted a write, the close happens when that write ends)."""
        if self._closed:
            return
        if self._owner == threading.get_ident():     # we interrupted our own write()
            self._pending = dict(summary or {})
            return
        if not self._lock.acquire(timeout=5.0):      # another thread is stuck in write()
            self._pending = dict(summary or {})
            return
        try:
            if self._closed:
                return
            summary = {**(self._pending or {}), **(summary or {})}
            self._pending = None
            t_end = self._t_last if self._t_last is not None else 0.0
            full = {"clean": True,
                    "duration_s": (t_end - self._t_first) if self._t_first is not None else 0.0,
                    "messages": dict(self.counts), "write_error": str(self.error or "") or None,
                    **(summary or {})}
            if self.error is None:
                self._append("/summary", t_end, encode({"t": t_end, **full}))
            try:
                self._writer.finish()
                self._file.flush()
                os.fsync(self._file.fileno())
            except (OSError, ValueError) as exc:
                self.error = self.error or exc
            self._closed = True
            self._stop_sync.set()
            try:
                self._file.close()
            except OSError:
                pass
        finally:
            self._lock.release()

    def __enter__(self) -> "FlightLog":
        return self

    def __exit__(self, *exc) -> None:
        self.close()
