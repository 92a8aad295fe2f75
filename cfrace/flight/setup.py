"""The race set-up, resolved once at the edge (the CLI) and passed down: track, drone profile,
checked policies, geofence. Everything here can fail (one-line CfraceError) and nothing here
touches a drone: `cfrace fly` resolves it before it opens the mocap or any link.

And the race's I/O as factories (RaceIO): the runner gets its clock, its links and its mocap
source from them and knows nothing else of where they come from (radio, UDP, an in-process
simulator, a lockstep clock, fault injection: cfrace.rehearsal.dryrun builds those).
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

from cfrace.drone import DroneProfile, load_profile
from cfrace.contract.actions import action_map_constants
from cfrace.contract.observations import LAYOUTS, ObsLayout
from cfrace.errors import CfraceError, ConfigError, PolicyError
from cfrace.flight.loop.clock import RealClock
from cfrace.flight.config import FlightConfig
from cfrace.flight.mocap.consistency import STILL_S
from cfrace.flight.link.opener import link_factory, stop_log_path
from cfrace.flight.mocap.sources import open_mocap
from cfrace.flight.safety.check import CommandLimits, Fence
from cfrace.loopmodel import IDLE_THRUST_COUNTS, idle_floor_w
from cfrace.policy import OnnxPolicy, resolve_policy
from cfrace.paths import CALIBRATION_DIR
from cfrace.track import Track, ground_start_positions, load_track


@dataclass(frozen=True)
class CheckedPolicy:
    """A policy loaded and checked against the race (track, obstacles, layout, loop rate)."""

    policy: OnnxPolicy
    path: Path
    layout: ObsLayout
    decimation: int            #: loop ticks per policy step (rate_hz / policy_hz)


@dataclass(frozen=True)
class RaceSetup:
    """What one race flies, resolved once: cfg plus the objects its names stand for."""

    cfg: FlightConfig
    track: Track
    profile: DroneProfile
    policies: tuple[CheckedPolicy, ...]   #: one per drone, ego first (a repeated policy: the same object)
    fence: Fence
    limits: CommandLimits                 #: what a sent setpoint may hold (the profile's)
    notes: tuple[str, ...] = ()           #: warnings for the start-up banner (idle_floor_notes)


def check_policy(cfg: FlightConfig, track: Track, spec: str, profile: DroneProfile | None = None) -> CheckedPolicy:
    """One policy, loaded and checked BEFORE anything flies (PolicyError naming the file); with a
    profile, its action map must stay within the profile's body rates and thrust."""
    path = resolve_policy(spec, track.name, cfg.obstacles)
    pol = OnnxPolicy(path)
    pol.check(track.name, cfg.obstacles)
    meta = pol.meta
    if profile is not None:
        for key, mine, most in (("max_rates_deg", meta["max_rates_deg"], profile.max_rates_deg),
                                ("max_thrust_weights", [meta["max_thrust_weights"]], [profile.max_thrust_weights])):
            if any(not v <= m * (1 + 1e-9) for v, m in zip(mine, most)):
                raise PolicyError(f"{path}: metadata {key}={meta[key]!r} exceeds drone profile "
                                  f"{profile.name}'s {list(most) if len(most) > 1 else most[0]!r}")
    layout = LAYOUTS[meta["obs_layout"]]
    dec = cfg.rate_hz / meta["policy_hz"]
    if abs(dec - round(dec)) > 1e-6 or round(dec) < 1:
        raise PolicyError(f"{path}: policy_hz {meta['policy_hz']:g} does not divide the {cfg.rate_hz:g} Hz loop")
    if layout.world_position != cfg.obstacles:
        raise PolicyError(f"{path}: layout {layout.name} does not fit a race "
                          f"{'with' if cfg.obstacles else 'without'} obstacles")
    return CheckedPolicy(pol, Path(path), layout, int(round(dec)))


def resolve_race(cfg: FlightConfig, track: Track | None = None) -> RaceSetup:
    """Load the track (unless given), the profile and every drone's policy and check them together.
    A policy named more than once is loaded once: its drones share one ONNX session, and the tick
    runs them in one batched call."""
    track = track if track is not None else load_track(cfg.track)
    ground_start_positions(track, len(cfg.specs))   # the field fits the start grid inside the arena, else one line
    profile = load_profile(cfg.profile)
    loaded: dict[str, CheckedPolicy] = {}
    for spec in cfg.specs:
        if spec not in loaded:
            loaded[spec] = check_policy(cfg, track, spec, profile)
    policies = tuple(loaded[spec] for spec in cfg.specs)
    return RaceSetup(cfg, track, profile, policies, Fence.from_track(track, cfg.safety.geofence_margin_m),
                     CommandLimits.from_profile(profile), idle_floor_notes(profile, dict(zip(cfg.names, policies))))


def idle_floor_notes(profile: DroneProfile, policies: dict) -> tuple[str, ...]:
    """One line per policy ({drone name: CheckedPolicy}) that did not train with the profile's idle
    floor. An armed Crazyflie 2.1 Brushless floors every motor at powerDist.idleThrust, 7000 counts
    in its build (power_distribution_quadrotor.c, powerDistributionCap: a floor, not an offset, so
    commands above it pass unchanged and no thrust mapping can undo it; IDLE_THRUST_COUNTS). A
    policy trained without it asks for less in its dives and gets the floor; one trained with
    ``--span-profiles`` naming the profile met it (metadata drone_ranges)."""
    floor = idle_floor_w(profile)
    if floor <= 0.0:
        return ()
    notes = []
    for name, p in policies.items():
        meta = p.policy.meta
        if profile.name in (meta.get("drone_ranges") or {}).get("profiles", ()):
            continue
        notes.append(f"{name}: {p.path.name} trained on {meta.get('drone_profile', 'another profile')} without the "
                     f"idle floor of {profile.name} ({IDLE_THRUST_COUNTS[profile.name]:.0f} counts per motor, "
                     f"{floor:.2f} of its weight): a real {profile.name} delivers at least that whatever the policy asks "
                     f"(rehearse it: cfrace sim dry-run --idle-thrust {IDLE_THRUST_COUNTS[profile.name]:.0f})")
    return tuple(notes)


def training_profile(track: Track, ego: str, obstacles: bool, default: str = "cf21bl") -> str:
    """The drone profile the ego policy was trained for (metadata drone_profile). ConfigError (one
    line) when no profile of that name is in calibration/, or when the one there is not the one it
    trained on (its action-map constants, recorded in the metadata, differ): a policy trained on a
    profile file elsewhere (`--profile PATH`) needs that path again. ``default`` only for a policy
    that does not load or names no profile (its error surfaces later, in resolve_race)."""
    try:
        meta = OnnxPolicy(resolve_policy(ego, track.name, obstacles)).meta
        name = meta["drone_profile"]
    except (CfraceError, KeyError):
        return default
    try:
        prof = load_profile(name)
    except CfraceError:
        raise ConfigError(f"--profile trained: {ego} was trained on drone profile {name!r}, which is not in "
                          f"{CALIBRATION_DIR}; give --profile PATH (its YAML)") from None
    recorded = {k: meta.get(k) for k in action_map_constants(prof)}
    if recorded != action_map_constants(prof):
        raise ConfigError(f"--profile trained: {ego} was trained on a drone profile {name!r} other than "
                          f"{CALIBRATION_DIR / name}.yaml (max thrust or body rates differ); give --profile PATH "
                          f"(its YAML)")
    return name


@dataclass(frozen=True)
class RaceIO:
    """Where a race's clock, links and mocap come from.

    open_mocap(): a MocapSource, not yet opened; open_link(index, uri): the Link of drone ``index``,
    not yet connected; clock: RealClock (the loop thread is then pinned and SCHED_FIFO as
    configured) or a LockstepClock (neither); link_clock(): the time the links stamp what they
    hear with; prewarm_s: the clock's warm-up window before each tick (0 = none); uris: one link
    URI per drone, ego first; hooks: an object with before_tick/filter_obs/filter_action called by
    the loop and a ``log`` list stored as the result's "faults" (fault injection), or None."""

    open_mocap: Callable[[], object]
    open_link: Callable[[int, str], object]
    clock: object
    link_clock: Callable[[], float]
    prewarm_s: float
    uris: tuple[str, ...]
    hooks: object | None = None
    still_s: float = 0.0    #: s the poses must stay still before the set-up (0: no check; consistency.check_still)
    wait: Callable[[float], None] | None = None   #: lets time pass outside the loop (None: time.sleep)


def check_pose_source(mocap: str, uris) -> None:
    """A pose source must belong to the drones it steers: recorded poses (replay://) fly no link
    but null:// ones, the in-process simulator's (sim) only its own sim:// drones, and the pose
    stream of `cfrace sim serve` (sim://HOST:PORT) only its simulated drones over udp://."""
    real = [u for u in uris if not u.startswith("null://")]
    if mocap.startswith("replay://") and real:
        raise ConfigError(f"--mocap {mocap}: recorded poses belong to the recorded drones, not to {real[0]} "
                          f"(a replay flies null:// links only)")
    if mocap == "sim" and any(not u.startswith("sim://") for u in real):
        raise ConfigError("--mocap sim: the in-process simulator's poses steer its own sim:// drones only")
    if mocap.startswith("sim://") and any(not u.startswith("udp://") for u in real):
        raise ConfigError(f"--mocap {mocap}: the poses of `cfrace sim serve` belong to its simulated drones "
                          f"(udp:// links), not to {next(u for u in real if not u.startswith('udp://'))}")


def real_io(cfg: FlightConfig) -> RaceIO:
    """Real drones: cflib links to cfg.uris held by the link keeper process, the mocap source
    cfg.mocap, the wall clock; the poses must be still before the set-up (consistency.check_still)."""
    from cfrace.flight.link.radio import check_radios

    if len(cfg.uris) != len(cfg.specs):
        raise ConfigError(f"--uris: need {len(cfg.specs)} link URIs (one per drone), got {list(cfg.uris)}")
    check_pose_source(cfg.mocap, cfg.uris)
    check_radios(cfg.uris, cfg.rate_hz)
    links = link_factory(cfg.uris, heartbeat_s=cfg.safety.overrun_stop_s, stop_log=stop_log_path(cfg.log),
                         rt_priority=cfg.rt_priority, loop_cpu=cfg.loop_cpu, estop_watchdog=cfg.estop_watchdog)
    return RaceIO(open_mocap=lambda: open_mocap(cfg.mocap, bodies=list(cfg.bodies)),
                  open_link=links, clock=RealClock(cfg.dt), link_clock=time.monotonic,
                  prewarm_s=cfg.prewarm_s, uris=tuple(cfg.uris),
                  still_s=STILL_S if any(not u.startswith("null://") for u in cfg.uris) else 0.0)
