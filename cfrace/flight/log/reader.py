"""Reading a flight log (cfrace.flight.log.writer writes it), also a truncated one: everything
up to the last complete record. JSON records are decoded lazily; the Foxglove scene's messages
(other encodings) are kept as bytes with their channel's encodings."""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from pathlib import Path

from mcap.exceptions import EndOfFile, InvalidMagic, McapError
from mcap.records import Channel, Message, Schema
from mcap.stream_reader import StreamReader

from cfrace.errors import LogError

class _StrictFile:
    """A read-only file whose short reads raise EndOfFile (the mcap reader would accept them)."""

    def __init__(self, f):
        self._f = f
        self.clean_eof = False   #: the file ended exactly where a record would start

    def read(self, n: int = -1) -> bytes:
        data = self._f.read(n)
        if n is not None and n >= 0 and len(data) < n:
            self.clean_eof = n == 1 and not data    # only an opcode read asks for 1 byte
            raise EndOfFile()
        return data


@dataclass
class FlightLogData:
    """Everything a flight log holds. messages(topic) -> [(t, dict)], decoded on first use."""

    path: Path
    meta: dict
    summary: dict | None
    truncated: bool
    stop_reason: str = ""                                   #: why reading stopped early
    raw: dict[str, list[bytes]] = field(default_factory=dict)   #: topic -> JSON payloads
    #: topic -> payloads of the channels in other encodings (the Foxglove scene: protobuf)
    other: dict[str, list[bytes]] = field(default_factory=dict)
    #: topic -> (message encoding, schema name, schema encoding) of every channel
    channels: dict[str, tuple[str, str, str]] = field(default_factory=dict)
    bad_messages: int = 0                                   #: payloads that did not decode
    _decoded: dict[str, list[tuple[float, dict]]] = field(default_factory=dict, repr=False)

    @property
    def topics(self) -> list[str]:
        return list(self.raw) + list(self.other)

    @property
    def complete(self) -> bool:
        """True when the writer closed the log cleanly and nothing was cut off."""
        return self.summary is not None and not self.truncated

    def count(self, topic: str) -> int:
        return len(self.raw.get(topic, ()) or self.other.get(topic, ()))

    def messages(self, topic: str) -> list[tuple[float, dict]]:
        if topic not in self._decoded:
            out = []
            for data in self.raw.get(topic, ()):
                try:
                    msg = json.loads(data)
                    t = float(msg.pop("t"))
                except (ValueError, KeyError, TypeError, AttributeError):
                    self.bad_messages += 1
                    continue
                out.append((t, msg))
            self._decoded[topic] = out
        return self._decoded[topic]

    @property
    def duration_s(self) -> float:
        if self.summary and isinstance(self.summary.get("duration_s"), (int, float)):
            return float(self.summary["duration_s"])
        times = [m[0] for topic in self.raw if topic not in ("/meta", "/summary")
                 for m in self.messages(topic)]
        return (max(times) - min(times)) if times else 0.0


class _Records:
    """What read_log keeps of the records: payloads per topic (JSON ones apart) and each channel's
    (message encoding, schema name, schema encoding)."""

    def __init__(self):
        self.raw: dict[str, list[bytes]] = {}
        self.other: dict[str, list[bytes]] = {}
        self.channels: dict[str, tuple[str, str, str]] = {}
        self._topics: dict[int, str] = {}
        self._json: set[int] = set()
        self._schemas: dict[int, tuple[str, str]] = {}

    def add(self, record) -> None:
        if isinstance(record, Channel):
            self._topics[record.id] = record.topic
            self.channels[record.topic] = (record.message_encoding, *self._schemas.get(record.schema_id, ("", "")))
            if record.message_encoding == "json":
                self._json.add(record.id)
        elif isinstance(record, Message):
            topic = self._topics.get(record.channel_id)
            if topic is None:
                raise ValueError(f"message on unknown channel {record.channel_id}")
            (self.raw if record.channel_id in self._json else self.other).setdefault(topic, []).append(record.data)
        elif isinstance(record, Schema):
            self._schemas[record.id] = (record.name, record.encoding)


def read_log(path: str | Path) -> FlightLogData:
    """Read a flight log, also a truncated one (everything before the damage; truncated=True).
    Raises LogError (one line naming the file) if it is missing, not MCAP or has no /meta."""
    path = Path(path)
    try:
        f = open(path, "rb")
        size = os.fstat(f.fileno()).st_size
    except OSError as exc:
        raise LogError(f"cannot read flight log {path}: {exc.strerror or exc}") from None
    found = _Records()
    truncated, reason = True, "file ends without the MCAP footer"
    with f:
        strict = _StrictFile(f)
        records = StreamReader(strict, record_size_limit=max(size, 1)).records
        try:
            while True:
                try:
                    record = next(records)
                except StopIteration:
                    truncated, reason = False, ""
                    break
                found.add(record)
        except InvalidMagic:
            if f.tell() <= 8:
                raise LogError(f"{path} is not an MCAP flight log (bad magic bytes)") from None
            reason = "bad magic at the end"
        except EndOfFile:
            if size < 8:
                raise LogError(f"{path} is not an MCAP flight log ({size} bytes)") from None
            reason = ("ends after a complete record without the MCAP footer (writer stopped)"
                      if strict.clean_eof else f"cut off inside a record at byte {size}")
        except (McapError, ValueError, UnicodeDecodeError, OverflowError, MemoryError) as exc:
            if f.tell() <= 8:
                raise LogError(f"{path} is not an MCAP flight log") from None
            reason = f"damaged record near byte {f.tell()}: {exc}"
    data = FlightLogData(path=path, meta={}, summary=None, truncated=truncated, stop_reason=reason,
                         raw=found.raw, other=found.other, channels=found.channels)
    metas = data.messages("/meta")
    if not metas:
        raise LogError(f"{path} is not a cfrace flight log (no /meta message)" if not truncated else
                       f"{path}: an MCAP file cut before its first message ({reason}), nothing to read")
    data.meta = metas[0][1]
    summaries = data.messages("/summary")
    data.summary = summaries[-1][1] if summaries else None
    return data
