"""Race tracks: gates in race order, gate geometry, obstacles, arena and spawn parameters.

Pure geometry on numpy arrays; the simulator and the flight stack convert to torch as needed.
Conventions (the authors' training code, Jirl-upenn/AgileFlight_MultiAgent
ma_quadcopter_env.py): a gate pose is [x, y, z, yaw]; the gate normal is
n = (cos yaw, sin yaw, 0); a gate is passed flying from the +n side to the -n side.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cfrace.errors import ConfigError
from cfrace.paths import TRACKS_DIR
from cfrace.yamlcfg import Reader, open_named

ARENA_MAX_M = 1000.0   #: m, the largest arena coordinate a track may have (a room, not a fence to nowhere)


@dataclass(frozen=True)
class GateGeometry:
    opening: float = 1.0     #: m, inner square opening side
    border: float = 0.2      #: m, frame width (outer side = opening + 2 border)
    thickness: float = 0.04  #: m, along the gate normal

    @property
    def outer(self) -> float:
        return self.opening + 2.0 * self.border


@dataclass(frozen=True)
class Obstacle:
    center: tuple[float, float]         #: m, box centre in the xy plane (stands on the floor)
    size: tuple[float, float, float]    #: m, box extent along its own x, y, z
    yaw: float                          #: rad


@dataclass(frozen=True)
class Arena:
    x: tuple[float, float]   #: m, allowed x range
    y: tuple[float, float]   #: m, allowed y range
    z_max: float             #: m, ceiling

    def outside_xy(self, xy) -> np.ndarray:
        """(...) bool: the points (..., >=2) [x, y] m lie outside the arena's floor plan (the
        simulator's arena crash rule and the flight fence's soft limit both start there)."""
        p = np.asarray(xy, dtype=np.float64)
        return (p[..., 0] < self.x[0]) | (p[..., 0] > self.x[1]) | (p[..., 1] < self.y[0]) | (p[..., 1] > self.y[1])


@dataclass(frozen=True)
class Spawn:
    gate_distance: tuple[float, float] = (0.6, 1.6)  #: m, start distance before a gate
    lateral: float = 0.3                             #: m, start jitter
    opponent_offset: float = 0.4                     #: m, side-by-side distance of two drones
    opponent_stagger: float = 0.0                    #: m, one drone this much further back (random which)
    ground_start_prob: float = 0.25                  #: share of ground starts
    ground_distance: float = 1.5                     #: m, ground start distance before gate 0


#: rad, a training start's heading is the gate's reverse normal +- this (uniform; cfrace.env.race_env)
HEADING_JITTER_RAD = 0.3


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


def start_grid(spawn: Spawn, gate: GateGeometry, drones: int) -> np.ndarray:
    """(N, 2) start slots of an N-drone field, [sideways, back] in m, relative to the grid's centre
    (the spawn point): rows of as many drones as fit side by side ``spawn.opponent_offset`` apart
    inside the gate opening (floor(opening / offset), at least 1), each row centred, rows one offset
    (or ``opponent_stagger`` if larger) apart and centred on the spawn distance, so that every row
    starts as near the spawn distance as the field allows (the shipped policies take off from the
    ground 0.6-1.2 m before gate 0, not 1.4 m: docs/flight.md). Two drones: one row of two."""
    if drones < 1:
        raise ValueError(f"a start grid needs at least 1 drone, got {drones}")
    offset = max(spawn.opponent_offset, 1e-3)
    per_row = max(1, int(math.floor(gate.opening / offset + 1e-9)))
    spacing = max(offset, spawn.opponent_stagger)
    slots = []
    for s in range(drones):
        row, col = divmod(s, per_row)
        in_row = min(per_row, drones - row * per_row)
        slots.append(((col - (in_row - 1) / 2.0) * offset, row * spacing))
    out = np.asarray(slots, dtype=np.float64)
    rows = (drones - 1) // per_row + 1
    out[:, 1] -= (rows - 1) * spacing / 2.0
    return out


@dataclass(frozen=True)
class Track:
    name: str
    gates: tuple[tuple[float, float, float, float], ...]  #: race order, [x, y, z, yaw]
    gate: GateGeometry
    obstacles: tuple[Obstacle, ...]
    arena: Arena
    spawn: Spawn
    source: str = ""

    @property
    def num_gates(self) -> int:
        return len(self.gates)

    def gate_array(self) -> np.ndarray:
        """(G, 4) float64 [x, y, z, yaw]."""
        return np.asarray(self.gates, dtype=np.float64)

    def gate_rotations(self) -> np.ndarray:
        """(G, 3, 3) world-from-gate rotations (yaw about z)."""
        yaw = self.gate_array()[:, 3]
        c, s = np.cos(yaw), np.sin(yaw)
        rot = np.zeros((len(yaw), 3, 3))
        rot[:, 0, 0], rot[:, 0, 1] = c, -s
        rot[:, 1, 0], rot[:, 1, 1] = s, c
        rot[:, 2, 2] = 1.0
        return rot

    def gate_corners(self) -> np.ndarray:
        """(G, 4, 3) world positions of the opening corners in the observation order
        (0,+d,+d), (0,-d,+d), (0,-d,-d), (0,+d,-d), d = opening / 2."""
        d = self.gate.opening / 2.0
        local = np.array([[0, d, d], [0, -d, d], [0, -d, -d], [0, d, -d]], dtype=np.float64)
        return self.gate_array()[:, None, :3] + np.einsum("gij,cj->gci", self.gate_rotations(), local)

    def gate_bars(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The frames as boxes: centres (G*4, 3), half extents (G*4, 3), yaw (G*4,).

        Bars per gate in the gate frame: top, bottom (full outer width), left, right."""
        o, b, t = self.gate.opening / 2.0, self.gate.border, self.gate.thickness / 2.0
        outer = o + b
        local_c = np.array([[0, 0, o + b / 2], [0, 0, -o - b / 2], [0, o + b / 2, 0], [0, -o - b / 2, 0]])
        half = np.array([[t, outer, b / 2], [t, outer, b / 2], [t, b / 2, o], [t, b / 2, o]])
        rot = self.gate_rotations()
        centres = self.gate_array()[:, None, :3] + np.einsum("gij,cj->gci", rot, local_c)
        g = self.num_gates
        yaw = np.repeat(self.gate_array()[:, 3], 4)
        return centres.reshape(g * 4, 3), np.tile(half, (g, 1)), yaw

    def obstacle_boxes(self, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Obstacles as boxes: centres (K, 3), half extents (K, 3), yaw (K,).

        ``scale`` in [0, 1] (the obstacle curriculum, ``cfrace train --obstacle-curriculum``): each
        box's horizontal extents times ``scale``, shrunk towards its anchor (obstacle_anchors), the
        height kept. 1 is the track as defined."""
        if not 0.0 <= scale <= 1.0:
            raise ValueError(f"obstacle scale must be in [0, 1], got {scale}")
        if not self.obstacles:
            return np.zeros((0, 3)), np.zeros((0, 3)), np.zeros((0,))
        c = np.array([[o.center[0], o.center[1], o.size[2] / 2] for o in self.obstacles])
        h = np.array([o.size for o in self.obstacles]) / 2.0
        y = np.array([o.yaw for o in self.obstacles])
        if scale != 1.0:
            anchors = self.obstacle_anchors()
            c[:, :2] = anchors + scale * (c[:, :2] - anchors)
            h[:, :2] *= scale
        return c, h, y

    def obstacle_anchors(self) -> np.ndarray:
        """(K, 2) m, the point each obstacle shrinks towards in the obstacle curriculum: the end of
        its long horizontal axis nearest the centre of the first obstacle it overlaps (so that
        obstacles that join into one barrier stay joined while they grow, and a path around the
        barrier's free end moves out continuously), or its centre if it overlaps none."""
        c, h, y = self.obstacle_boxes()
        out = c[:, :2].copy()
        for k in range(len(c)):
            other = next((j for j in range(len(c)) if j != k and boxes_overlap(c[k], h[k], y[k], c[j], h[j], y[j])),
                         None)
            if other is None:
                continue
            long = 0 if h[k, 0] >= h[k, 1] else 1
            axis = (np.array([math.cos(y[k]), math.sin(y[k])]) if long == 0
                    else np.array([-math.sin(y[k]), math.cos(y[k])]))
            ends = c[k, :2] + np.outer([h[k, long], -h[k, long]], axis)
            out[k] = ends[np.argmin(np.linalg.norm(ends - c[other, :2], axis=1))]
        return out

    def without_obstacles(self) -> "Track":
        return Track(self.name, self.gates, self.gate, (), self.arena, self.spawn, self.source)


def obstacle_scale(iteration: int, curriculum: int) -> float:
    """The obstacles' size (Track.obstacle_boxes scale) in training iteration ``iteration`` (0-based)
    of a run with ``--obstacle-curriculum curriculum``: from 0 at the first iteration linearly to 1
    at iteration ``curriculum``, full size after (and always full size without a curriculum)."""
    if curriculum <= 0:
        return 1.0
    return min(1.0, max(0, iteration) / curriculum)


def boxes_overlap(c1, h1, yaw1: float, c2, h2, yaw2: float) -> bool:
    """Exact overlap test of two boxes yawed about z (separating axes in xy, intervals in z)."""
    c1, h1, c2, h2 = (np.asarray(v, dtype=np.float64) for v in (c1, h1, c2, h2))
    if abs(c1[2] - c2[2]) >= h1[2] + h2[2]:
        return False
    axes = []
    for yaw in (yaw1, yaw2):
        axes += [np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])]
    d = c2[:2] - c1[:2]
    for axis in axes:
        r1 = sum(h1[k] * abs(axis @ a) for k, a in enumerate(axes[:2]))
        r2 = sum(h2[k] * abs(axis @ a) for k, a in enumerate(axes[2:]))
        if abs(axis @ d) >= r1 + r2:
            return False
    return True


def _validate(track: Track, r: Reader) -> None:
    a = track.arena
    if a.x[0] >= a.x[1] or a.y[0] >= a.y[1]:
        raise r.fail("arena", "ranges must be [low, high] with low < high")
    half_outer = track.gate.outer / 2.0
    if track.gate.border <= 0 or track.gate.opening <= 0:
        raise r.fail("gate", "opening and border must be > 0")
    for i, (x, y, z, yaw) in enumerate(track.gates):
        if not (a.x[0] <= x <= a.x[1] and a.y[0] <= y <= a.y[1]):
            raise r.fail(f"gates[{i}]", f"gate centre ({x}, {y}) is outside the arena x {list(a.x)}, y {list(a.y)}")
        side = track.gate.opening / 2.0 * np.array([-math.sin(yaw), math.cos(yaw)])   # the opening, across the path
        for end in (np.array([x, y]) + side, np.array([x, y]) - side):
            if not (a.x[0] <= end[0] <= a.x[1] and a.y[0] <= end[1] <= a.y[1]):
                raise r.fail(f"gates[{i}]", f"the gate's opening reaches ({end[0]:.2f}, {end[1]:.2f}), outside the "
                                            f"arena x {list(a.x)}, y {list(a.y)}")
        if z - half_outer < 0.0 or z + half_outer > a.z_max:
            raise r.fail(f"gates[{i}]", f"gate frame z [{z - half_outer:.2f}, {z + half_outer:.2f}] m "
                         f"is outside floor 0 .. ceiling {a.z_max}")
    # obstacles must not block a gate opening (the opening as a thin box in the gate plane)
    half_open = (track.gate.thickness / 2.0, track.gate.opening / 2.0, track.gate.opening / 2.0)
    for i, gate in enumerate(track.gates):
        for k, (c, h, yaw) in enumerate(zip(*track.obstacle_boxes())):
            if boxes_overlap(gate[:3], half_open, gate[3], c, h, yaw):
                raise r.fail(f"obstacles[{k}]", f"obstacle passes through the opening of gate {i}")
    if len(track.gates) < 2:
        raise r.fail("gates", "a track needs at least 2 gates")


def load_track(name_or_path: str | Path) -> Track:
    """Load a track by name (tracks/NAME.yaml) or path; strict, ConfigError on any problem."""
    r = open_named(name_or_path, TRACKS_DIR, "track")
    name = r.file_name(TRACKS_DIR)
    g = r.mapping("gate", {})
    gate = GateGeometry(g.number("opening", 1.0, positive=True), g.number("border", 0.2, positive=True),
                        g.number("thickness", 0.04, positive=True))
    g.done()
    raw_gates = r.sequence("gates")
    gates = tuple(r.check_vector(f"gates[{i}]", v, 4) for i, v in enumerate(raw_gates))
    obstacles = []
    for i, item in enumerate(r.sequence("obstacles", [])):
        o = r.child(f"obstacles[{i}]", item)
        obstacles.append(Obstacle(o.vector("center", 2), o.vector("size", 3, positive=True), o.number("yaw", 0.0)))
        o.done()
    ar = r.mapping("arena")
    arena = Arena(ar.vector("x", 2, min=-ARENA_MAX_M, max=ARENA_MAX_M),
                  ar.vector("y", 2, min=-ARENA_MAX_M, max=ARENA_MAX_M), ar.number("z_max", positive=True, max=ARENA_MAX_M))
    ar.done()
    sp = r.mapping("spawn", {})
    d = Spawn()
    spawn = Spawn(gate_distance=sp.vector("gate_distance", 2, d.gate_distance, positive=True),
                  lateral=sp.number("lateral", d.lateral, min=0.0),
                  opponent_offset=sp.number("opponent_offset", d.opponent_offset, min=0.0),
                  ground_start_prob=sp.number("ground_start_prob", d.ground_start_prob, min=0.0, max=1.0),
                  ground_distance=sp.number("ground_distance", d.ground_distance, positive=True),
                  opponent_stagger=sp.number("opponent_stagger", d.opponent_stagger, min=0.0))
    sp.done()
    r.done()
    track = Track(name, gates, gate, tuple(obstacles), arena, spawn, source=r.path)
    _validate(track, r)
    return track


def list_tracks() -> list[Path]:
    return sorted(TRACKS_DIR.glob("*.yaml"))


def _ground_slots(track: "Track", drones: int) -> np.ndarray:
    """(drones, 2) [x, y] m of the start grid on the floor (ground_start_positions)."""
    gx, gy, _, gyaw = track.gates[0]
    n = np.array([math.cos(gyaw), math.sin(gyaw)])
    lateral = np.array([-n[1], n[0]])
    centre = np.array([gx, gy]) + track.spawn.ground_distance * n
    grid = start_grid(track.spawn, track.gate, drones)             # (N, 2) [sideways, back] m
    return centre + grid[:, :1] * lateral + grid[:, 1:] * n


def ground_start_positions(track: "Track", drones: int, floor_z: float = 0.0) -> tuple[np.ndarray, float]:
    """(drones, 3) positions on the floor in the track's start grid (start_grid: two side by side,
    spawn.opponent_offset apart; more in rows behind each other), its rows centred on
    track.spawn.ground_distance before gate 0 on its +n side, at height floor_z; and the yaw (rad)
    facing gate 0. Where a ground start's drones stand: the simulated drones
    (cfrace.simcf.firmware), the hover start's targets and the take-off check of a flight
    (cfrace.flight.loop.swarm). ConfigError if a slot lies outside the arena (a drone would start
    outside the flight's fence soft limit, or crash at once in the simulator), saying how many
    drones fit."""
    xy = _ground_slots(track, drones)
    out = np.nonzero(track.arena.outside_xy(xy))[0]
    if len(out):
        fit = max([k for k in range(1, drones) if not track.arena.outside_xy(_ground_slots(track, k)).any()], default=0)
        i, a = int(out[0]), track.arena
        raise ConfigError(f"{drones} drones do not fit the {track.name} track's start grid: drone {i + 1}'s slot "
                          f"({xy[i, 0]:.2f}, {xy[i, 1]:.2f}) m lies outside the arena (x {a.x[0]:g}..{a.x[1]:g}, "
                          f"y {a.y[0]:g}..{a.y[1]:g} m); at most {fit} drones start there")
    pos = np.zeros((drones, 3))
    pos[:, :2] = xy
    pos[:, 2] = floor_z
    _, _, _, gyaw = track.gates[0]
    return pos, _wrap(gyaw + math.pi)
