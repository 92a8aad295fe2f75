"""The 6-axis force/torque sensor of the thrust stand: its CAN frames, described by SENSOR.yaml.

One description serves both ends: ``decode`` turns received CAN frames into samples in the drone's
body frame (x forward, y left, z up; N and N m about the drone's centre), ``encode`` turns the
simulated stand's true forces into the frames the sensor would send (cfrace sim stand). See
docs/calibration.md for the file format; shipped examples are in calibration/sensors/.
"""

from __future__ import annotations

import struct
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.errors import ConfigError
from cfrace.paths import CALIBRATION_DIR
from cfrace.yamlcfg import Reader, read_named

SENSORS_DIR = CALIBRATION_DIR / "sensors"
QUANTITIES = ("fx", "fy", "fz", "tx", "ty", "tz")   #: force N, torque N m, sensor axes
#: field type -> (struct code, bytes)
FIELD_TYPES = {"int8": ("b", 1), "uint8": ("B", 1), "int16": ("h", 2), "uint16": ("H", 2),
               "int32": ("i", 4), "uint32": ("I", 4), "float32": ("f", 4)}
_AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Field:
    quantity: str    #: one of QUANTITIES or "counter"
    byte: int        #: offset in the frame's data
    ftype: str       #: one of FIELD_TYPES
    scale: float     #: physical unit per count (N or N m; 1 for the counter)

    @property
    def limits(self) -> tuple[float, float] | None:
        """(min, max) raw count of an integer field (a reading there is saturated), None for floats."""
        if self.ftype == "float32":
            return None
        bits = 8 * FIELD_TYPES[self.ftype][1]
        return (0, 2 ** bits - 1) if self.ftype.startswith("u") else (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1)


@dataclass(frozen=True)
class Frame:
    can_id: int
    extended: bool
    length: int                 #: data length code, bytes
    fields: tuple[Field, ...]


@dataclass(frozen=True)
class SensorSpec:
    name: str
    description: str
    rate_hz: float                           #: samples per second the sensor sends
    byte_order: str                          #: "little" | "big"
    frames: tuple[Frame, ...]                #: one sample = one of each, in this order
    axes: tuple[tuple[int, float], ...]      #: body axis k = sign * sensor axis index
    offset: tuple[float, float, float]       #: m, drone centre in the body-aligned sensor frame
    force_range: tuple[float, float, float]  #: N, |f| per body axis beyond which the run stops
    torque_range: tuple[float, float, float]  #: N m, same for torques
    tare_samples: int                        #: samples averaged for the bias with motors off
    timeout_s: float                         #: no complete sample for this long -> CAN timeout
    source: str = ""

    @property
    def counter(self) -> Field | None:
        for fr in self.frames:
            for f in fr.fields:
                if f.quantity == "counter":
                    return f
        return None

    def ids(self) -> str:
        return ", ".join(f"0x{fr.can_id:X}" for fr in self.frames)

    # ------------------------------------------------------------ frames <-> sensor values
    def _fmt(self, f: Field) -> str:
        return ("<" if self.byte_order == "little" else ">") + FIELD_TYPES[f.ftype][0]

    def decode(self, frame_index: int, data: bytes) -> tuple[dict, bool]:
        """One frame's data -> ({quantity: value in N / N m (counter: raw)}, saturated?)."""
        fr = self.frames[frame_index]
        if len(data) < fr.length:
            raise ValueError(f"frame 0x{fr.can_id:X}: {len(data)} data bytes, expected {fr.length}")
        out, sat = {}, False
        for f in fr.fields:
            (raw,) = struct.unpack_from(self._fmt(f), data, f.byte)
            lim = f.limits
            if f.quantity != "counter" and lim is not None and raw in lim:
                sat = True
            out[f.quantity] = raw if f.quantity == "counter" else raw * f.scale
        return out, sat

    def encode(self, values: dict, counter: int = 0) -> list[tuple[int, bool, bytes]]:
        """Sensor-axis values {quantity: N or N m} -> [(can_id, extended, data)], integer fields
        rounded and clipped to their type's range as a real sensor's converter saturates."""
        frames = []
        for fr in self.frames:
            data = bytearray(fr.length)
            for f in fr.fields:
                if f.quantity == "counter":
                    lo, hi = f.limits
                    raw = counter % (hi + 1) if lo == 0 else counter
                else:
                    raw = float(values[f.quantity]) / f.scale
                    lim = f.limits
                    if lim is not None:
                        raw = int(min(max(round(raw), lim[0]), lim[1]))
                struct.pack_into(self._fmt(f), data, f.byte, raw)
            frames.append((fr.can_id, fr.extended, bytes(data)))
        return frames

    # ------------------------------------------------------------ sensor frame <-> body frame
    def to_body(self, sensor: np.ndarray) -> np.ndarray:
        """(..., 6) [fx fy fz tx ty tz] sensor axes -> body frame about the drone's centre."""
        sensor = np.asarray(sensor, dtype=np.float64)
        f = np.stack([s * sensor[..., k] for k, s in self.axes], -1)
        t = np.stack([s * sensor[..., 3 + k] for k, s in self.axes], -1)
        # torque about the drone's centre r: tau_c = tau_o - r x f (r from the sensor origin)
        t = t - np.cross(np.asarray(self.offset), f)
        return np.concatenate([f, t], -1)

    def from_body(self, body: np.ndarray) -> np.ndarray:
        """Inverse of to_body: (..., 6) body wrench about the drone's centre -> sensor axes."""
        body = np.asarray(body, dtype=np.float64)
        f, t = body[..., :3], body[..., 3:] + np.cross(np.asarray(self.offset), body[..., :3])
        out = np.zeros(body.shape[:-1] + (6,))
        for b, (k, s) in enumerate(self.axes):
            out[..., k] = s * f[..., b]
            out[..., 3 + k] = s * t[..., b]
        return out


def _axes(r: Reader) -> tuple[tuple[int, float], ...]:
    a = r.mapping("axes")
    out = []
    for axis in _AXES:
        text = a.string(axis)
        t = text.strip()
        sign = -1.0 if t.startswith("-") else 1.0
        name = t.lstrip("+-")
        if name not in _AXES:
            raise a.fail(axis, f"expected +x, -x, +y, -y, +z or -z (the sensor axis along body {axis}), got {text!r}")
        out.append((_AXES.index(name), sign))
    a.done()
    if sorted(k for k, _ in out) != [0, 1, 2]:
        raise r.fail("axes", "each sensor axis must be used once (a signed permutation of x, y, z)")
    if np.linalg.det(np.array([[s if k == j else 0.0 for j in range(3)] for k, s in out])) < 0:
        raise r.fail("axes", "left-handed: the mapping must be a rotation (flip one more sign)")
    return tuple(out)


def _frame(r: Reader, k: int, item) -> Frame:
    fr = r.child(f"frames[{k}]", item)
    can_id = fr.raw("can_id")
    extended = fr.raw("extended", False)
    if not isinstance(extended, bool):
        raise fr.fail("extended", f"expected true or false, got {extended!r}")
    if isinstance(can_id, bool) or not isinstance(can_id, int) or not 0 <= can_id <= (0x1FFFFFFF if extended else 0x7FF):
        raise fr.fail("can_id", f"expected an {'29' if extended else '11'}-bit CAN id, got {can_id!r}")
    length = int(fr.number("length", 8, min=1, max=8))
    fields = []
    for j, fitem in enumerate(fr.sequence("fields")):
        f = fr.child(f"fields[{j}]", fitem)
        q = f.string("quantity")
        if q not in QUANTITIES + ("counter",):
            raise f.fail("quantity", f"expected one of {', '.join(QUANTITIES)} or counter, got {q!r}")
        ftype = f.string("type")
        if ftype not in FIELD_TYPES:
            raise f.fail("type", f"expected one of {', '.join(FIELD_TYPES)}, got {ftype!r}")
        byte = f.number("byte", min=0, max=7)
        if byte != int(byte) or byte + FIELD_TYPES[ftype][1] > length:
            raise f.fail("byte", f"a {ftype} at byte {byte:g} does not fit in {length} data bytes")
        if q == "counter":
            if ftype in ("float32",) or ftype.startswith("int"):
                raise f.fail("type", "the counter must be an unsigned integer (uint8, uint16, uint32)")
            scale = 1.0
        else:
            scale = f.number("scale")
            if scale == 0.0:
                raise f.fail("scale", "must not be 0")
        f.done()
        fields.append(Field(q, int(byte), ftype, scale))
    if not fields:
        raise fr.fail("fields", "a frame needs at least one field")
    spans = sorted((f.byte, f.byte + FIELD_TYPES[f.ftype][1]) for f in fields)
    for (a0, a1), (b0, _) in zip(spans, spans[1:]):
        if b0 < a1:
            raise fr.fail("fields", f"fields overlap at byte {b0}")
    fr.done()
    return Frame(can_id, extended, length, tuple(fields))


def load_sensor(name_or_path: str | Path) -> SensorSpec:
    """Load a sensor description by name (calibration/sensors/NAME.yaml) or path; strict, one-line errors."""
    r = read_named(name_or_path, SENSORS_DIR, "sensor description")
    name = r.string("name")
    description = r.string("description") if r.has("description") else ""
    rate = r.number("rate_hz", positive=True)
    order = r.string("byte_order", "little")
    if order not in ("little", "big"):
        raise r.fail("byte_order", f"expected little or big, got {order!r}")
    frames = tuple(_frame(r, k, item) for k, item in enumerate(r.sequence("frames")))
    if not frames:
        raise r.fail("frames", "needs at least one frame")
    ids = [(fr.can_id, fr.extended) for fr in frames]
    if len(set(ids)) != len(ids):
        raise r.fail("frames", "two frames share a CAN id")
    quantities = [f.quantity for fr in frames for f in fr.fields]
    for q in QUANTITIES:
        if quantities.count(q) != 1:
            raise r.fail("frames", f"{q} must appear in exactly one field, found {quantities.count(q)}")
    counters = [fr for fr in frames if any(f.quantity == "counter" for f in fr.fields)]
    if counters and len(counters) != len(frames):
        raise r.fail("frames", "a counter must be in every frame (it ties the frames of one sample) or in none")
    axes = _axes(r)
    offset = r.vector("offset", 3, (0.0, 0.0, 0.0))
    rng = r.mapping("range")
    force_range = rng.vector("force", 3, positive=True)
    torque_range = rng.vector("torque", 3, positive=True)
    rng.done()
    tare = r.mapping("tare", {})
    tare_samples = int(tare.number("samples", 200, min=10))
    tare.done()
    timeout = r.number("timeout_ms", 50.0, positive=True) / 1000.0
    r.done()
    return SensorSpec(name, description, rate, order, frames, axes, offset, force_range, torque_range,
                      tare_samples, timeout, r.path)
