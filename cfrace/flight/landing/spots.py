"""Where landing drones go: per drone a spot on the floor inside the arena, clear of the gates'
frames, the obstacles and the other drones (their spots and where they are), as near as possible to
where the drone will have stopped, reachable in a straight line that crosses no gate and no obstacle
(``choose_landing_spots``: greedy in drone order; each spot then blocks the next drones), and the
geometry of paths seen from above. The manoeuvre itself: cfrace.flight.landing.descent."""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np

@dataclass(frozen=True)
class LandingConfig:
    """Limits of the landing manoeuvre (m, m/s, s)."""

    wall_margin_m: float = 0.5        #: spots this far inside the arena's walls
    gate_clearance_m: float = 0.6     #: from a gate frame's footprint on the floor
    obstacle_clearance_m: float = 0.5  #: from an obstacle's box
    drone_separation_m: float = 0.8   #: between spots, and from other drones
    grid_m: float = 0.1               #: spacing of the candidate spots
    path_clearance_m: float = 0.15    #: the straight path to the spot stays this far from obstacles and gates
    path_separation_m: float = 0.3    #: ... and this far from the other drones' paths and from drones that stay
    max_tries: int = 100              #: nearest free spots whose path is checked; none clear: land where it stops
    approach_height_m: float = 0.25   #: height of the go-to to the spot, before the vertical landing
    approach_speed_mps: float = 1.0   #: mean speed of the go-to (its duration: distance / speed, >= 1 s)
    descent_s: float = 1.5            #: duration of the final land from approach_height_m ...
    land_height_m: float = -0.05      #: ... to this height: below the floor, so that the drone is down
                                      #: (not a few cm up, lagging the plan) when the planner turns the motors off
    brake_done_mps: float = 0.3       #: braking ends below this speed ...
    brake_max_s: float = 1.5          #: ... or after this long
    hold_max_s: float = 2.5           #: a braked drone waits at most this long for another one's path to clear
    #: while other drones race: spots this far from the race line seen from above (the straight lines from
    #: gate to gate), where a downed drone would lie in a racing drone's way (the opponent_down rule)
    race_line_clearance_m: float = 1.0
    #: ... and at most this far from where the drone stops, on its own side of the race line (its go-to,
    #: at racing height at first, crosses no gate-to-gate line); else any spot
    race_line_detour_m: float = 2.0


def _seg_point_dist(a: np.ndarray, b: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance of points p (K, 2) to the segment a-b (2,)."""
    d = b - a
    t = np.clip(((p - a) @ d) / max(float(d @ d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(p - (a + t[:, None] * d), axis=1)


def _segments_cross(p1, p2, q1, q2):
    """Do the 2D segments p1-p2 and q1-q2 intersect (touching counts)? Points (2,), or (K, 2) for
    K segments at once (then (K,) bool)."""
    def orient(a, b, c):
        return (b[..., 0] - a[..., 0]) * (c[..., 1] - a[..., 1]) - (b[..., 1] - a[..., 1]) * (c[..., 0] - a[..., 0])
    p1, p2, q1, q2 = (np.asarray(v, np.float64) for v in (p1, p2, q1, q2))
    d1, d2 = orient(q1, q2, p1), orient(q1, q2, p2)
    d3, d4 = orient(p1, p2, q1), orient(p1, p2, q2)
    return (d1 * d2 <= 0.0) & (d3 * d4 <= 0.0)


def segment_gap(p1, p2, q1, q2) -> float:
    """Distance (m) between the 2D segments p1-p2 and q1-q2 (0 where they cross)."""
    if _segments_cross(p1, p2, q1, q2):
        return 0.0
    p1, p2, q1, q2 = (np.asarray(v, np.float64)[:2] for v in (p1, p2, q1, q2))
    return float(min(_seg_point_dist(q1, q2, np.stack([p1, p2])).min(), _seg_point_dist(p1, p2, np.stack([q1, q2])).min()))


def gate_footprints(track) -> list[tuple[np.ndarray, np.ndarray]]:
    """Each gate's frame seen from above: the segment (2,) - (2,) of its outer width."""
    out = []
    half = track.gate.outer / 2.0
    for x, y, _, yaw in track.gates:
        lateral = np.array([-math.sin(yaw), math.cos(yaw)])
        c = np.array([x, y])
        out.append((c - half * lateral, c + half * lateral))
    return out


def _obstacle_dist(track, pts: np.ndarray) -> np.ndarray:
    """Distance of points (K, 2) to the nearest obstacle box footprint (inf without obstacles)."""
    best = np.full(len(pts), np.inf)
    for o in track.obstacles:
        c, s = math.cos(o.yaw), math.sin(o.yaw)
        rel = pts - np.asarray(o.center, np.float64)
        local = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)
        outside = np.maximum(np.abs(local) - np.array(o.size[:2]) / 2.0, 0.0)
        best = np.minimum(best, np.linalg.norm(outside, axis=1))
    return best


def _to_segments(start: np.ndarray, ends: np.ndarray, p: np.ndarray) -> np.ndarray:
    """Distance (K,) of the point p (2,) to each segment start-ends[k] (ends (K, 2))."""
    d = ends - start
    t = np.clip(((p - start) @ d.T) / np.maximum(np.einsum("ij,ij->i", d, d), 1e-12), 0.0, 1.0)
    return np.linalg.norm(start + t[:, None] * d - p, axis=1)


def _apart(start: np.ndarray, ends: np.ndarray, paths, still, separation: float) -> np.ndarray:
    """(K,) bool: the straight path start-ends[k] keeps ``separation`` from every path (a, b) of
    ``paths`` (other drones flying to their spots at the same time) and from the points ``still``,
    or, where a drone starts nearer than that, no less than at the start (it is where it is)."""
    ok = np.ones(len(ends), bool)
    for q in still:
        q = np.asarray(q, np.float64)[:2]
        ok &= _to_segments(start, ends, q) >= min(separation, float(np.linalg.norm(start - q))) - 1e-9
    for a, b in paths:
        cross = _segments_cross(start, ends, a, b)
        at_start = float(_seg_point_dist(a, b, start[None])[0])
        near = np.minimum.reduce([_to_segments(start, ends, a), _to_segments(start, ends, b),
                                  _seg_point_dist(a, b, ends), np.full(len(ends), at_start)])
        ok &= ~cross & (near >= min(separation, at_start) - 1e-9)
    return ok


def path_clear(track, start: np.ndarray, end: np.ndarray, clearance: float) -> bool:
    """The straight path start-end (2,) crosses no gate footprint and keeps ``clearance`` from the gate
    footprints and the obstacles (points of the path already closer at the start do not count: the
    drone is where it is; near a gate the path must lead away from it, not along its frame)."""
    return bool(paths_clear(track, start, np.asarray(end, np.float64)[None, :2], clearance)[0])


def paths_clear(track, start: np.ndarray, ends: np.ndarray, clearance: float) -> np.ndarray:
    """(K,) bool: path_clear for each path start-ends[k] (ends (K, 2)), all at once: each path is
    sampled every 5 cm (its own count of points; the shorter ones padded and the padding ignored)."""
    start, ends = np.asarray(start, np.float64)[:2], np.asarray(ends, np.float64).reshape(-1, 2)
    ok = np.ones(len(ends), bool)
    footprints = gate_footprints(track)
    for a, b in footprints:
        if _seg_point_dist(a, b, start[None])[0] > 1e-6:
            ok &= ~_segments_cross(start, ends, a, b)
    n = np.maximum(2, (np.linalg.norm(ends - start, axis=1) / 0.05).astype(int) + 1)       # (K,) points per path
    j = np.arange(n.max())
    valid = j < n[:, None]                                                                  # (K, N)
    pts = start + (np.minimum(j, n[:, None] - 1) / (n[:, None] - 1))[..., None] * (ends - start)[:, None]
    flat = pts.reshape(-1, 2)
    if footprints:
        gd = np.minimum.reduce([_seg_point_dist(a, b, flat) for a, b in footprints]).reshape(valid.shape)
        rise = np.diff(gd, axis=1, prepend=-np.inf)
        leaving = rise >= 0.5 * np.linalg.norm(pts[:, 1] - pts[:, 0], axis=1)[:, None]     # at 30 deg or more
        ok &= np.all((gd >= clearance) | leaving | ~valid, axis=1)
    if track.obstacles:
        d = _obstacle_dist(track, flat).reshape(valid.shape)
        ok &= np.all((d >= clearance) | (d >= d[:, :1] - 1e-9) | ~valid, axis=1)
    return ok


def race_line(track) -> list[tuple[np.ndarray, np.ndarray]]:
    """The race line seen from above: the straight lines (2,) - (2,) from each gate's centre to the
    next one's, round the lap."""
    centres = np.asarray(track.gates, np.float64)[:, :2]
    return list(zip(centres, np.roll(centres, -1, 0)))


def race_line_dist(track, pts: np.ndarray) -> np.ndarray:
    """Distance (K,) of points (K, 2) to the race line (race_line)."""
    return np.minimum.reduce([_seg_point_dist(a, b, pts) for a, b in race_line(track)])


def _beside_line(track, start: np.ndarray, ends: np.ndarray, cfg: LandingConfig) -> np.ndarray:
    """(K,) bool: the go-to start-ends[k] is at most race_line_detour_m long and crosses no line of
    the race line (the off-line spots' extra rule while others race)."""
    ok = np.linalg.norm(ends - start, axis=1) <= cfg.race_line_detour_m
    for a, b in race_line(track):
        ok &= ~_segments_cross(start, ends, a, b)
    return ok


@functools.lru_cache(maxsize=8)
def candidate_spots(track, cfg: LandingConfig = LandingConfig(), off_line: bool = False) -> np.ndarray:
    """(K, 2) floor points inside the arena that are clear of gates and obstacles, and with
    ``off_line`` of the race line (race_line_clearance_m) as well (computed once per track, config and
    kind: a read-only array)."""
    if off_line:
        pts = candidate_spots(track, cfg)
        out = pts[race_line_dist(track, pts) >= cfg.race_line_clearance_m]
        out.flags.writeable = False
        return out
    a = track.arena
    xs = np.arange(a.x[0] + cfg.wall_margin_m, a.x[1] - cfg.wall_margin_m + 1e-9, cfg.grid_m)
    ys = np.arange(a.y[0] + cfg.wall_margin_m, a.y[1] - cfg.wall_margin_m + 1e-9, cfg.grid_m)
    pts = np.stack(np.meshgrid(xs, ys, indexing="ij"), axis=-1).reshape(-1, 2)
    ok = _obstacle_dist(track, pts) >= cfg.obstacle_clearance_m
    for g0, g1 in gate_footprints(track):
        ok &= _seg_point_dist(g0, g1, pts) >= cfg.gate_clearance_m
    out = pts[ok]
    out.flags.writeable = False
    return out


#: candidate spots a drone's choice looks at first, the nearest to where it stops (the whole arena
#: only when none of them will do): the choice runs in the tick, and on a large arena (the complex
#: track: 15 k candidates) checking every candidate against every other drone's path made the tick in
#: which eight drones start landing overrun the loop (tests/test_flight_landing.py, docs/flight.md)
NEAR_CANDIDATES = 1500
#: of the max_tries nearest allowed spots, how many _nearest checks first (the rest in one batch)
NEAR_FIRST = 8
#: candidates in the first step of _nearest's walk outwards (the rule on other drones' paths is applied
#: to these); each step takes twice as many as the one before, so that a rule that rejects most spots
#: is done in a few steps, not a dozen
RULE_CHUNK = 128


def _nearest(track, stop, cand, order, clear, rule, cfg: LandingConfig):
    """The nearest candidate allowed by ``clear`` (K,) and ``rule`` (cand (k, 2) -> (k,) bool) and
    reachable in a straight line, among the max_tries nearest allowed ones (this runs in the tick):
    (that spot or None, whether max_tries allowed ones were there to look at). The rule is applied in
    distance order a chunk at a time (doubling), only as far as the search goes."""
    order, seen, lo, size = order[clear[order]], 0, 0, RULE_CHUNK
    while lo < len(order):
        idx = order[lo:lo + size]
        lo, size = lo + size, 2 * size
        idx = idx[rule(cand[idx])][:cfg.max_tries - seen]
        for chunk in (idx[:NEAR_FIRST], idx[NEAR_FIRST:]):   # the nearest few first: mostly one of them will do
            ok = paths_clear(track, stop, cand[chunk], cfg.path_clearance_m) if len(chunk) else chunk.astype(bool)
            if ok.any():
                return cand[chunk[int(np.argmax(ok))]], True
        seen += len(idx)
        if seen >= cfg.max_tries:
            return None, True
    return None, False


def choose_landing_spots(track, stops, others=(), cfg: LandingConfig = LandingConfig(), paths=(),
                         off_line: bool = False) -> np.ndarray:
    """Landing spots (N, 2) for drones expected to stop at ``stops`` (N, 2 or 3) m; ``others`` (M, 2 or 3):
    drones that will not move (e.g. already down) and must be kept clear of; ``paths``: (start, spot)
    of drones flying to their spots already, whose paths the new ones must neither cross nor come
    within path_separation_m of; ``off_line`` (other drones still race): spots off the race line
    (candidate_spots), any spot only if none of those is free. ValueError if the arena has no free spot
    left for some drone."""
    if off_line:
        try:
            return _choose(track, stops, others, cfg, paths, candidate_spots(track, cfg, True), True)
        except ValueError:
            pass
    return _choose(track, stops, others, cfg, paths, candidate_spots(track, cfg), False)


def _choose(track, stops, others, cfg: LandingConfig, paths, everything: np.ndarray, off_line: bool) -> np.ndarray:
    """choose_landing_spots among the candidate spots ``everything``; ``off_line``: every rule also asks
    for a go-to beside the race line (_beside_line), and a drone does not land where it stops if that
    lies near the line."""
    stops = np.asarray(stops, np.float64).reshape(-1, np.shape(stops)[-1])[:, :2]
    blocked = [np.asarray(o, np.float64)[:2] for o in others]
    if not len(everything):
        raise ValueError("no candidate landing spot in the arena")
    still = list(blocked)
    spots = np.zeros((len(stops), 2))
    paths = [(np.asarray(a, np.float64)[:2], np.asarray(b, np.float64)[:2]) for a, b in paths]   # flown already
    for i, stop in enumerate(stops):
        dist = np.linalg.norm(everything - stop, axis=1)
        near = np.argpartition(dist, NEAR_CANDIDATES)[:NEAR_CANDIDATES] if len(dist) > NEAR_CANDIDATES else None
        pending = blocked + [stops[j] for j in range(i + 1, len(stops))]
        @functools.cache
        def candidates(idx: int) -> tuple:
            """(candidates, nearest first, clear of the pending drones): the nearest ones (0) or all (1)."""
            sel = near if idx == 0 and near is not None else slice(None)
            cand = everything[sel]
            ok = np.ones(len(cand), bool)
            for b in pending:
                ok &= np.linalg.norm(cand - b, axis=1) >= cfg.drone_separation_m
            return cand, np.argsort(dist[sel]), ok

        def nearest(rule, far: bool = True) -> np.ndarray | None:
            """The nearest allowed candidate under ``rule`` (cand -> extra mask): among the nearest
            candidates first, then (none of them allowed, and ``far``) the whole arena: the same spot
            either way."""
            allowed = (lambda cand: rule(cand) & _beside_line(track, stop, cand, cfg)) if off_line else rule
            for idx in (((0, 1) if far else (0,)) if near is not None else (1,)):
                found, enough = _nearest(track, stop, *candidates(idx), allowed, cfg)
                if found is not None or enough:
                    return found          # the max_tries nearest allowed ones overall were all looked at
            return None

        # a spot whose path keeps clear of the other drones' paths, among the NEAR_CANDIDATES nearest
        # (a drone hemmed in by other paths would make this rule walk the whole arena: 25-100 ms of CPU
        # in the tick); else straight down where the drone stops if that is clear of them; else clear of
        # the drones that stay; else merely free (its go-to then waits for the others: failsafe._may_go)
        chosen = nearest(lambda cand: _apart(stop, cand, paths, still, cfg.path_separation_m), far=False)
        sep = cfg.path_separation_m
        if chosen is None and paths and all(_seg_point_dist(a, b, stop[None])[0] >= sep for a, b in paths) \
                and all(np.linalg.norm(stop - np.asarray(q)[:2]) >= sep for q in still) \
                and not (off_line and race_line_dist(track, stop[None])[0] < cfg.race_line_clearance_m):
            chosen = stop.copy()
        for rule in (lambda cand: _apart(stop, cand, (), still, cfg.path_separation_m),
                     lambda cand: np.ones(len(cand), bool)):
            if chosen is None:
                chosen = nearest(rule)
        if chosen is None:
            raise ValueError(f"no free landing spot in the arena for drone {i}")
        spots[i] = chosen
        blocked.append(chosen)
        paths.append((stop, chosen))
    return spots


def swap_pays(a, spot_a, b, spot_b, margin: float = 0.05) -> bool:
    """Drones at a and b (2,) fly straight to spot_a and spot_b: are the two paths together at least
    ``margin`` m shorter with the spots swapped? Then the swapped paths do not cross (crossing
    straight paths can always be uncrossed into a shorter pair)."""
    n = np.linalg.norm
    return bool(n(a - spot_b) + n(b - spot_a) + margin < n(a - spot_a) + n(b - spot_b))
