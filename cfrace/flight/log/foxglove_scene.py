"""Flights in Foxglove: the 3D scene and plottable commands, in the flight log and served live.

Built with the Foxglove SDK (`foxglove-sdk`, the `foxglove` extra): its well-known message types
(SceneUpdate, FrameTransforms) encode the messages and give their protobuf schemas, and its
WebSocket server serves them live (`--foxglove [PORT]`, loopback). The flight log file stays
cfrace's own writer (cfrace.flight.log.writer): the SDK's MCAP writer buffers whole chunks, and
a killed flight would lose them (docs/flight-log.md, "Foxglove"; tests/test_foxglove.py measures
it); the SDK's schemas and encoded bytes go into our file as they are.

Topics (docs/flight-log.md):
  /foxglove/scene       SceneUpdate      the track: gate frames (one cube per bar), obstacles
                                         (cubes), arena and geofence (line boxes), gate numbers;
                                         at the start and once a second (late live clients)
  /foxglove/tf          FrameTransforms  world -> each body, from every /estimate with a valid pose
  /foxglove/drones      SceneUpdate      each drone (a box in its body frame) and its trail (the
                                         last TRAIL_S of positions, world frame), TRAIL_HZ
  /foxglove/command/B   JSON             commanded body rates (deg/s) and thrust (N, counts) of
                                         body B, every tick: plottable

SceneSink is what the flight loop writes to (its `log`): every record goes to the flight log as
before, and the scene messages made from it go to the log and to the live server.
"""

from __future__ import annotations

import json
import math
import time
from collections import deque

import numpy as np

from cfrace.errors import ConfigError

WORLD = "world"          #: the frame of the track and the mocap
TRAIL_S = 3.0            #: s of trail per drone
TRAIL_HZ = 10.0          #: Hz, drone boxes and trails
SCENE_EVERY_S = 1.0      #: s between repeats of the static scene
DRONE_SIZE = (0.12, 0.12, 0.04)   #: m, the box drawn for a drone
COLORS = ((0.12, 0.47, 0.71), (1.0, 0.5, 0.05), (0.17, 0.63, 0.17), (0.58, 0.4, 0.74))   #: per drone, rgb

#: JSON schema of /foxglove/command/BODY
COMMAND_SCHEMA = {
    "type": "object", "title": "cfrace command", "description": "the setpoint sent to one drone this tick",
    "properties": {
        "t": {"type": "number", "description": "s, flight clock"},
        "roll_rate_dps": {"type": "number"}, "pitch_rate_dps": {"type": "number"},
        "yaw_rate_dps": {"type": "number"}, "thrust_n": {"type": ["number", "null"]},
        "thrust_counts": {"type": "integer"}, "stopped": {"type": "boolean"}}}


def available() -> bool:
    """Whether the Foxglove SDK is installed (`pip install -e ".[foxglove]"`)."""
    import importlib.util
    return importlib.util.find_spec("foxglove") is not None


def _sdk():
    try:
        import foxglove
        from foxglove import messages
    except ImportError:
        raise ConfigError("Foxglove needs the foxglove extra: pip install -e \".[foxglove]\"") from None
    return foxglove, messages


class Encoded:
    """One encoded message: topic, schema (name, encoding, bytes), message encoding, payload."""

    __slots__ = ("topic", "schema", "encoding", "data")

    def __init__(self, topic: str, schema: tuple[str, str, bytes], encoding: str, data: bytes):
        self.topic, self.schema, self.encoding, self.data = topic, schema, encoding, data


def _stamp(m, ns: int):
    return m.Timestamp(sec=ns // 1_000_000_000, nsec=ns % 1_000_000_000)


def _yaw_quat(m, yaw: float):
    return m.Quaternion(x=0.0, y=0.0, z=math.sin(yaw / 2.0), w=math.cos(yaw / 2.0))


def _box_edges(lo, hi) -> list[tuple[float, float, float]]:
    """The 12 edges of an axis-aligned box as 24 points (LINE_LIST)."""
    x0, y0, z0 = lo
    x1, y1, z1 = hi
    c = [(x0, y0, z0), (x1, y0, z0), (x1, y1, z0), (x0, y1, z0), (x0, y0, z1), (x1, y0, z1), (x1, y1, z1), (x0, y1, z1)]
    pairs = [(0, 1), (1, 2), (2, 3), (3, 0), (4, 5), (5, 6), (6, 7), (7, 4), (0, 4), (1, 5), (2, 6), (3, 7)]
    return [c[i] for p in pairs for i in p]


class FoxgloveScene:
    """Foxglove messages from what the flight loop logs. ``static()``: the track scene (encoded
    once); ``messages(topic, t, msg, ns)``: those made from one log record (the caller's wall-clock
    ns stamp). Pure apart from the trails it keeps."""

    def __init__(self, track, fence, bodies: list[str], obstacles: bool):
        fg, m = _sdk()
        self.m = m
        self.bodies = list(bodies)
        self.colors = {b: COLORS[i % len(COLORS)] for i, b in enumerate(self.bodies)}
        self._trail = {b: deque(maxlen=max(2, int(TRAIL_S * TRAIL_HZ))) for b in self.bodies}
        self._next_drones = -math.inf
        self._schemas = {}
        for name in ("SceneUpdate", "FrameTransforms"):
            s = getattr(m, name).get_schema()
            self._schemas[name] = (s.name, s.encoding, bytes(s.data))
        self._command_schema = ("cfrace.Command", "jsonschema", json.dumps(COMMAND_SCHEMA).encode())
        self._static = self._scene(track, fence, obstacles)

    # -- the track --------------------------------------------------------------------------
    def _color(self, rgb, a: float = 1.0):
        return self.m.Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=a)

    def _cubes(self, centres, halves, yaws, rgb, a: float):
        m = self.m
        return [m.CubePrimitive(pose=m.Pose(position=m.Vector3(x=float(c[0]), y=float(c[1]), z=float(c[2])),
                                            orientation=_yaw_quat(m, float(y))),
                                size=m.Vector3(x=2 * float(h[0]), y=2 * float(h[1]), z=2 * float(h[2])),
                                color=self._color(rgb, a))
                for c, h, y in zip(centres, halves, yaws)]

    def _lines(self, points, rgb, thickness: float):
        m = self.m
        return m.LinePrimitive(type=m.LinePrimitiveLineType.LineList, pose=m.Pose(
            position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
            thickness=thickness, scale_invariant=True, color=self._color(rgb),
            points=[m.Point3(x=float(p[0]), y=float(p[1]), z=float(p[2])) for p in points])

    def _scene(self, track, fence, obstacles: bool) -> Encoded:
        m = self.m
        a = track.arena
        entities = [m.SceneEntity(frame_id=WORLD, id="gates", cubes=self._cubes(*track.gate_bars(), (0.84, 0.15, 0.16), 0.9),
                                  texts=[m.TextPrimitive(pose=m.Pose(
                                      position=m.Vector3(x=float(g[0]), y=float(g[1]), z=float(g[2]) + track.gate.outer / 2 + 0.15),
                                      orientation=m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)),
                                      billboard=True, font_size=14.0, scale_invariant=True,
                                      color=self._color((1, 1, 1)), text=f"gate {i}")
                                      for i, g in enumerate(track.gate_array())]),
                    m.SceneEntity(frame_id=WORLD, id="arena", lines=[
                        self._lines(_box_edges((a.x[0], a.y[0], 0.0), (a.x[1], a.y[1], a.z_max)), (0.6, 0.6, 0.6), 1.5)])]
        lo = [v if math.isfinite(v) else 0.0 for v in fence.lo]
        entities.append(m.SceneEntity(frame_id=WORLD, id="geofence", lines=[
            self._lines(_box_edges(lo, fence.hi), (0.9, 0.2, 0.2), 1.0)]))
        if obstacles and track.obstacles:
            entities.append(m.SceneEntity(frame_id=WORLD, id="obstacles",
                                          cubes=self._cubes(*track.obstacle_boxes(), (0.5, 0.5, 0.55), 0.8)))
        return Encoded("/foxglove/scene", self._schemas["SceneUpdate"], "protobuf",
                       m.SceneUpdate(entities=entities).encode())

    def static(self) -> Encoded:
        return self._static

    # -- what the loop logs -----------------------------------------------------------------
    def messages(self, topic: str, t: float, msg: dict, ns: int) -> list[Encoded]:
        if topic == "/estimate":
            return self._poses(t, msg, ns)
        if topic == "/setpoint":
            return self._commands(t, msg)
        return []

    def _poses(self, t: float, msg: dict, ns: int) -> list[Encoded]:
        m = self.m
        stamp = _stamp(m, ns)
        tfs = []
        for body, e in msg.items():
            if not isinstance(e, dict) or not e.get("valid"):
                continue
            p, q = np.asarray(e["pos"], float), np.asarray(e["quat"], float)   # quat w, x, y, z
            if not (np.isfinite(p).all() and np.isfinite(q).all()):
                continue
            tfs.append(m.FrameTransform(timestamp=stamp, parent_frame_id=WORLD, child_frame_id=body,
                                        translation=m.Vector3(x=float(p[0]), y=float(p[1]), z=float(p[2])),
                                        rotation=m.Quaternion(x=float(q[1]), y=float(q[2]), z=float(q[3]),
                                                              w=float(q[0]))))
            if body in self._trail and t >= self._next_drones:
                self._trail[body].append((float(p[0]), float(p[1]), float(p[2])))
        out = []
        if tfs:
            out.append(Encoded("/foxglove/tf", self._schemas["FrameTransforms"], "protobuf",
                               m.FrameTransforms(transforms=tfs).encode()))
        if t >= self._next_drones:
            self._next_drones = t + 1.0 / TRAIL_HZ
            out.append(self._drones(stamp))
        return out

    def _drones(self, stamp) -> Encoded:
        m = self.m
        ident = m.Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
        entities = []
        for body in self.bodies:
            rgb = self.colors[body]
            entities.append(m.SceneEntity(timestamp=stamp, frame_id=body, id=f"drone/{body}", cubes=[
                m.CubePrimitive(pose=m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=ident),
                                size=m.Vector3(x=DRONE_SIZE[0], y=DRONE_SIZE[1], z=DRONE_SIZE[2]),
                                color=self._color(rgb))],
                texts=[m.TextPrimitive(pose=m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.12), orientation=ident),
                                       billboard=True, font_size=12.0, scale_invariant=True,
                                       color=self._color(rgb), text=body)]))
            trail = list(self._trail[body])
            if len(trail) >= 2:
                entities.append(m.SceneEntity(timestamp=stamp, frame_id=WORLD, id=f"trail/{body}", lines=[
                    m.LinePrimitive(type=m.LinePrimitiveLineType.LineStrip,
                                    pose=m.Pose(position=m.Vector3(x=0.0, y=0.0, z=0.0), orientation=ident),
                                    thickness=2.0, scale_invariant=True, color=self._color(rgb, 0.8),
                                    points=[m.Point3(x=x, y=y, z=z) for x, y, z in trail])]))
        return Encoded("/foxglove/drones", self._schemas["SceneUpdate"], "protobuf",
                       m.SceneUpdate(entities=entities).encode())

    def _commands(self, t: float, msg: dict) -> list[Encoded]:
        out = []
        for body, s in msg.items():
            if not isinstance(s, dict):
                continue
            r = [float(x) for x in s.get("rates_dps", (math.nan,) * 3)]
            thrust = s.get("thrust_n")
            doc = {"t": t, "roll_rate_dps": r[0], "pitch_rate_dps": r[1], "yaw_rate_dps": r[2],
                   "thrust_n": float(thrust) if thrust is not None and math.isfinite(thrust) else None,
                   "thrust_counts": int(s.get("thrust_counts", 0)), "stopped": bool(s.get("stopped"))}
            out.append(Encoded(f"/foxglove/command/{body}", self._command_schema, "json",
                               json.dumps(doc, allow_nan=False, separators=(",", ":")).encode()))
        return out


class LiveServer:
    """The SDK's WebSocket server on HOST:PORT (port 0: a free one), in a context of its own:
    publishes Encoded messages as they are (no second encoding)."""

    def __init__(self, port: int, host: str = "127.0.0.1"):
        fg, _ = _sdk()
        self._fg = fg
        self.context = fg.Context()
        try:
            self.server = fg.start_server(name="cfrace", host=host, port=int(port), context=self.context)
        except Exception as exc:  # noqa: BLE001 - the SDK raises its own error type (port in use, ...)
            raise ConfigError(f"--foxglove {port}: cannot serve on {host}:{port}: {exc}") from None
        self.host, self.port = host, int(self.server.port)
        self._channels: dict[str, object] = {}

    @property
    def url(self) -> str:
        return f"ws://{self.host}:{self.port}"

    def publish(self, enc: Encoded, ns: int) -> None:
        ch = self._channels.get(enc.topic)
        if ch is None:
            name, encoding, data = enc.schema
            ch = self._channels[enc.topic] = self._fg.Channel(
                enc.topic, schema=self._fg.Schema(name=name, encoding=encoding, data=data),
                message_encoding=enc.encoding, context=self.context)
        ch.log(enc.data, log_time=ns)

    def publish_json(self, topic: str, data: bytes, ns: int) -> None:
        """A cfrace JSON record (schema-less JSON channel)."""
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = self._fg.Channel(topic, message_encoding="json", context=self.context)
        ch.log(data, log_time=ns)

    def stop(self) -> None:
        try:
            self.server.stop()
        except Exception:  # noqa: BLE001 - stopping twice, or after the SDK shut down at exit
            pass


#: cfrace records the live server passes on as JSON (low rate: events, safety, race progress)
LIVE_JSON_TOPICS = ("/event", "/safety", "/race", "/link")


class SceneSink:
    """What the flight loop logs to: the flight log (or none) plus the Foxglove scene made from
    each record, written to that log and published on the live server (or neither)."""

    def __init__(self, log, scene: FoxgloveScene | None, server: LiveServer | None = None):
        self.log, self.scene, self.server = log, scene, server
        self._wall0_ns, self._mono0_ns = time.time_ns(), time.monotonic_ns()
        self._next_static = -math.inf
        self.error = None

    def _ns(self) -> int:
        return self._wall0_ns + time.monotonic_ns() - self._mono0_ns

    def _out(self, enc: Encoded, t: float, ns: int) -> None:
        if self.log is not None:
            self.log.write_encoded(enc.topic, t, enc.data, enc.schema, enc.encoding)
        if self.server is not None:
            self.server.publish(enc, ns)

    def write(self, topic: str, t: float, msg: dict) -> None:
        if self.log is not None:
            self.log.write(topic, t, msg)
        if self.scene is None:
            return
        try:
            ns = self._ns()
            if t >= self._next_static:
                self._next_static = t + SCENE_EVERY_S
                self._out(self.scene.static(), t, ns)
            for enc in self.scene.messages(topic, t, msg, ns):
                self._out(enc, t, ns)
            if self.server is not None and topic in LIVE_JSON_TOPICS:
                from cfrace.flight.log.writer import encode
                self.server.publish_json(topic, encode({"t": t, **msg}), ns)
        except Exception as exc:  # noqa: BLE001 - the scene must never end a flight
            self.error = exc
            self.scene = None

    @property
    def closed(self) -> bool:
        return self.log is None or self.log.closed

    def close(self, summary: dict | None = None) -> None:
        if self.log is not None:
            self.log.close(summary)
        if self.server is not None:
            self.server.stop()

    def __enter__(self) -> "SceneSink":
        return self

    def __exit__(self, *exc) -> None:
        self.close()


def log_write_error(sink) -> OSError | None:
    """The flight log file's first write error (FlightLog.error) behind what open_sink returned:
    a FlightLog, a SceneSink around one (its own ``error`` is the scene's) or None."""
    log = sink.log if isinstance(sink, SceneSink) else sink
    return None if log is None else log.error


def open_sink(log_path, meta: dict, track, fence, bodies: list[str], obstacles: bool,
              foxglove_port: int | None = None, scene: bool = True):
    """The flight's log sink: a FlightLog at log_path (None: no file), the Foxglove scene in it when
    the SDK is installed (and ``scene``), and the live server with foxglove_port (None: not
    served). Returns None when there is nothing to write to."""
    from cfrace.flight.log.writer import FlightLog

    if log_path is None and foxglove_port is None:
        return None
    server = LiveServer(foxglove_port) if foxglove_port is not None else None
    try:
        scene = FoxgloveScene(track, fence, bodies, obstacles) if (scene or server) and available() else None
        log = FlightLog(log_path, meta | {"foxglove": scene is not None}) if log_path is not None else None
    except BaseException:
        if server is not None:
            server.stop()
        raise
    if log is not None and scene is None and server is None:
        return log
    return SceneSink(log, scene, server)
