"""Piecewise polynomial trajectories of the high-level commander (the firmware's pptraj.c and
pptraj_compressed.c): the one polynomial evaluator of the simulated Crazyflie. The planner's own
moves (take-off, land, go-to, spiral: one 7th-order piece each) and the trajectories uploaded to
the trajectory memory (poly4d pieces, or the compressed format) are all `PiecewiseTrajectory`s.

Rules kept from the firmware (pptraj.c: piecewise_eval, piecewise_eval_reversed, poly4d_eval,
traj_eval_transform; pptraj_compressed.c: piecewise_compressed_load/_eval):

* a piece is x, y, z, yaw as polynomials of degree 7 (ascending coefficients) over its duration;
  ``timescale`` stretches time (2 = twice as long), each piece in turn;
* forward: the output is rotated about z by ``shift_yaw`` (position, velocity, acceleration; yaw
  plus ``shift_yaw``), then shifted by ``shift``; past the end the last piece's end point holds with
  zero velocity and acceleration;
* reversed: pieces from the last to the first, each run backwards (velocity negated), shifted by
  ``shift`` and never rotated (the firmware ignores the yaw shift there); past the end the first
  piece's start point holds;
* the compressed format: a start point (int16 mm x, y, z and 1/10 deg yaw) then pieces of a header
  byte (2 bits per coordinate: constant, linear, cubic Bezier, 7th-order Bezier), the duration in
  ms (uint16) and the control points after the first (int16 mm or 1/10 deg; the first is the end
  of the previous piece); a piece of duration 0 ends the trajectory.

Computed in float64 (the firmware: float32).
"""

from __future__ import annotations

import math
import struct
from dataclasses import dataclass, field

import numpy as np

from cfrace.drone import GRAVITY

PP_SIZE = 8                       #: coefficients per polynomial (degree 7)
POLY4D_BYTES = 4 * (4 * PP_SIZE + 1)   #: one poly4d piece in memory: 32 float32 coefficients + duration
COMPRESSED_POINTS = (0, 1, 3, 7)  #: control points stored per coordinate, by storage type
DISTANCE_SCALE = 1000.0           #: compressed distances are mm
ANGLE_SCALE = 1800.0 / math.pi    #: compressed angles are 1/10 deg


@dataclass
class Goal:
    """A trajectory evaluated at one instant."""

    pos: np.ndarray    #: m (3,)
    vel: np.ndarray    #: m/s (3,)
    acc: np.ndarray    #: m/s^2 (3,)
    yaw: float         #: rad
    yaw_rate: float    #: rad/s
    omega: np.ndarray = field(default_factory=lambda: np.zeros(3))   #: rad/s, body rates of the flat trajectory

    def finite(self) -> bool:
        return bool(all(np.all(np.isfinite(v)) for v in (self.pos, self.vel, self.acc, self.omega))
                    and math.isfinite(self.yaw) and math.isfinite(self.yaw_rate))


def poly7_nojerk(x0: float, v0: float, a0: float, x1: float, v1: float, a1: float, duration: float) -> np.ndarray:
    """Coefficients c (8,) of x(t) = sum c_k t^k on [0, duration] with the given position, velocity,
    acceleration at both ends and zero jerk at both ends (pptraj.c, poly7_nojerk)."""
    t = duration
    rows, rhs = [], []
    for tau, (x, v, a) in ((0.0, (x0, v0, a0)), (t, (x1, v1, a1))):
        for deriv, value in enumerate((x, v, a, 0.0)):
            row = np.zeros(PP_SIZE)
            for k in range(deriv, PP_SIZE):
                row[k] = math.perm(k, deriv) * tau ** (k - deriv)
            rows.append(row)
            rhs.append(value)
    return np.linalg.solve(np.array(rows), np.array(rhs))


def polyval(c, t: float, deriv: int = 0) -> float:
    """The ``deriv``-th derivative of sum c_k t^k at t."""
    return float(sum(math.perm(k, deriv) * c[k] * t ** (k - deriv) for k in range(deriv, len(c))))


def bezier_to_poly(points, duration: float) -> np.ndarray:
    """Coefficients (8,) on [0, duration] of the Bezier curve with these control points (1: constant,
    2: linear, 4: cubic, 8: degree 7), as the firmware's polybezier (pptraj.c)."""
    n = len(points) - 1
    c = np.zeros(PP_SIZE)
    for j in range(n + 1):   # power basis of s in [0, 1], then s = t / duration
        c[j] = math.comb(n, j) * sum((-1) ** (j - i) * math.comb(j, i) * points[i] for i in range(j + 1))
        c[j] /= duration ** j if j else 1.0
    return c


@dataclass
class Piece:
    coeffs: np.ndarray   #: (4, 8): x, y, z, yaw
    duration: float      #: s


class Poly4dMemory:
    """Pieces read from the trajectory memory at each access, as the firmware's trajectory points into
    its memory (an upload during the flight changes what is flown)."""

    def __init__(self, memory: bytearray, offset: int, n_pieces: int):
        self.memory, self.offset, self.n = memory, int(offset), int(n_pieces)

    def __len__(self) -> int:
        return self.n

    def __getitem__(self, k: int) -> Piece:
        if k < 0:
            k += self.n
        v = np.frombuffer(self.memory, "<f4", 4 * PP_SIZE + 1, self.offset + k * POLY4D_BYTES).astype(np.float64)
        return Piece(v[:4 * PP_SIZE].reshape(4, PP_SIZE), float(v[-1]))


def poly4d_bytes(pieces) -> bytes:
    """Pieces as the firmware stores them (cflib's Poly4D.pack): per piece x, y, z, yaw coefficients, duration."""
    return b"".join(struct.pack("<33f", *np.asarray(p.coeffs, np.float64).ravel(), p.duration) for p in pieces)


def decode_compressed(memory, offset: int) -> list[Piece]:
    """The pieces of a compressed trajectory at ``offset`` (pptraj_compressed.c: rewind, the piece
    headers, calculate_polynomial_coefficients). ValueError if it runs past the memory's end."""
    def take(n):
        nonlocal at
        if at + 2 * n > len(memory):
            raise ValueError(f"the compressed trajectory at offset {offset} runs past the end of the "
                             f"trajectory memory ({len(memory)} bytes)")
        vals = struct.unpack_from(f"<{n}h", memory, at)
        at += 2 * n
        return vals

    at = int(offset)
    x, y, z, yaw = take(4)
    end = [x / DISTANCE_SCALE, y / DISTANCE_SCALE, z / DISTANCE_SCALE, yaw / ANGLE_SCALE]
    pieces = []
    while True:
        if at + 3 > len(memory):
            take(2)   # raises
        header, ms = struct.unpack_from("<BH", memory, at)
        at += 3
        if ms == 0:
            return pieces
        duration = ms / 1000.0
        coeffs = np.zeros((4, PP_SIZE))
        for axis in range(4):
            kind = (header >> (2 * axis)) & 0x03
            scale = ANGLE_SCALE if axis == 3 else DISTANCE_SCALE
            points = [end[axis]] + [v / scale for v in take(COMPRESSED_POINTS[kind])]
            coeffs[axis] = bezier_to_poly(points, duration)
            end[axis] = points[-1]
        pieces.append(Piece(coeffs, duration))


def body_rates(acc: np.ndarray, jerk: np.ndarray, yaw: float, yaw_rate: float) -> np.ndarray:
    """The body rates (3,) rad/s of a drone flying the flat outputs (pptraj.c, poly4d_eval, from the
    differential flatness of a quadrotor): the thrust direction is acc + g; the jerk across it turns
    it (about body x and y), the yaw rate projected on it turns about body z."""
    thrust = acc + np.array([0.0, 0.0, GRAVITY])
    mag = float(np.linalg.norm(thrust))
    z_b = thrust / mag
    y_b = np.cross(z_b, [math.cos(yaw), math.sin(yaw), 0.0])
    y_b = y_b / np.linalg.norm(y_b)
    x_b = np.cross(y_b, z_b)
    h = (jerk - float(jerk @ z_b) * z_b) / mag
    return np.array([-float(h @ y_b), float(h @ x_b), z_b[2] * yaw_rate])


def _rotz(a: float) -> np.ndarray:
    c, s = math.cos(a), math.sin(a)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _wrap(a: float) -> float:
    return (a + math.pi) % (2.0 * math.pi) - math.pi


class PiecewiseTrajectory:
    """A sequence of pieces started at ``t_begin`` (s, simulated time)."""

    def __init__(self, pieces, t_begin: float, timescale: float = 1.0, reversed: bool = False):
        self.pieces = pieces
        self.t_begin = float(t_begin)
        self.timescale = np.float64(timescale)   # numpy: a zero timescale gives inf/nan as the firmware's floats
        self.reversed = bool(reversed)
        self.shift = np.zeros(3)
        self.shift_yaw = 0.0

    @property
    def duration(self) -> float:
        return sum(self.pieces[k].duration for k in range(len(self.pieces))) * self.timescale

    def finished(self, t: float) -> bool:
        return t - self.t_begin >= self.duration

    def _piece_eval(self, piece: Piece, tau: float, sign: float) -> Goal:
        """Piece at its own time tau, time stretched by the timescale; sign -1 runs it backwards."""
        with np.errstate(all="ignore"):
            ts = np.float64(self.timescale)
            vals = [[polyval(c, tau, d) * (sign / ts) ** d for c in piece.coeffs] for d in range(4)]
            acc, yaw, yaw_rate = np.array(vals[2][:3]), vals[0][3], vals[1][3]
            omega = body_rates(acc, np.array(vals[3][:3]), yaw, yaw_rate)
        return Goal(np.array(vals[0][:3]), np.array(vals[1][:3]), acc, yaw, yaw_rate, omega)

    @staticmethod
    def _held(goal: Goal) -> Goal:
        return Goal(goal.pos, np.zeros(3), np.zeros(3), goal.yaw, 0.0)   # omega zero too

    def eval(self, t: float) -> Goal:
        t = t - self.t_begin
        n = len(self.pieces)
        order = range(n - 1, -1, -1) if self.reversed else range(n)
        with np.errstate(all="ignore"):
            for k in order:
                piece = self.pieces[k]
                span = piece.duration * self.timescale
                if t <= span:
                    if self.reversed:
                        g = self._piece_eval(piece, piece.duration - t / self.timescale, -1.0)
                        g.pos = g.pos + self.shift
                        return g
                    return self._transform(self._piece_eval(piece, t / self.timescale, 1.0))
                t -= span
        if self.reversed:
            g = self._held(self._piece_eval(self.pieces[0], 0.0, 1.0))
            g.pos = g.pos + self.shift
            return g
        last = self.pieces[n - 1]
        return self._held(self._transform(self._piece_eval(last, last.duration, 1.0)))

    def _transform(self, g: Goal) -> Goal:
        """pptraj.c traj_eval_transform: rotate about z by shift_yaw, then shift."""
        rot = _rotz(_wrap(self.shift_yaw))
        return Goal(rot @ g.pos + self.shift, rot @ g.vel, rot @ g.acc, g.yaw + _wrap(self.shift_yaw), g.yaw_rate,
                    g.omega)

    def start_point(self) -> Goal:
        """The trajectory at its start (without shift), for relative starts (planner.c plan_start_trajectory)."""
        shift, shift_yaw = self.shift, self.shift_yaw
        self.shift, self.shift_yaw = np.zeros(3), 0.0
        try:
            return self.eval(self.t_begin)
        finally:
            self.shift, self.shift_yaw = shift, shift_yaw


def single_piece(start: Goal, end: Goal, duration: float, t_begin: float) -> PiecewiseTrajectory:
    """One 7th-order piece with zero jerk at both ends from ``start`` to ``end`` (position, velocity,
    acceleration; yaw and its rate) (pptraj.c piecewise_plan_7th_order_no_jerk)."""
    coeffs = np.stack([poly7_nojerk(start.pos[k], start.vel[k], start.acc[k], end.pos[k], end.vel[k], end.acc[k],
                                    duration) for k in range(3)]
                      + [poly7_nojerk(start.yaw, start.yaw_rate, 0.0, end.yaw, end.yaw_rate, 0.0, duration)])
    return PiecewiseTrajectory([Piece(coeffs, float(duration))], t_begin)
