"""Policies entering an evaluation: resolve, load, check against the track, name them.

A policy is given as a path or a short name (ours, ds, ss, dm) resolved in policies/ for the track
and obstacle setting. A policy that does not fit the track, the obstacle setting or its own
observation size is refused with a one-line PolicyError (the CLI exits with code 2).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

from cfrace.contract import METHODS, POLICY_HZ
from cfrace.drone import DroneProfile, load_profile
from cfrace.contract.observations import LAYOUTS, ObsLayout
from cfrace.errors import ConfigError, PolicyError
from cfrace.policy import OnnxPolicy, resolve_policy
from cfrace.track import Track, load_track


@dataclass(frozen=True)
class Entrant:
    name: str             #: display name (short name, or the file stem)
    path: Path
    policy: OnnxPolicy
    layout: ObsLayout     #: the observation layout its metadata names (each drone gets its own)

    @property
    def meta(self) -> dict:
        return self.policy.meta

    @property
    def method(self) -> str:
        return self.policy.meta["method"]

    @property
    def multi_agent(self) -> bool:
        return self.layout.opponent


def load_entrant(name_or_path: str | Path, track: Track, obstacles: bool) -> Entrant:
    """Resolve and load one policy; PolicyError when it does not fit ``track`` / ``obstacles``."""
    path = resolve_policy(name_or_path, track.name, obstacles)
    policy = OnnxPolicy(path)
    policy.check(track.name, obstacles)
    layout = LAYOUTS[policy.meta["obs_layout"]]
    if layout.dim != policy.obs_dim:  # validate_meta guarantees this; keep the promise explicit
        raise PolicyError(f"{path}: observation size {policy.obs_dim} does not fit layout {layout.name}")
    if abs(policy.meta["policy_hz"] - POLICY_HZ) > 1e-6:
        raise PolicyError(f"{path}: runs at {policy.meta['policy_hz']:g} Hz, evaluation steps policies at {POLICY_HZ:g} Hz")
    text = str(name_or_path)
    name = text if text in METHODS else path.stem
    return Entrant(name, path, policy, layout)


def load_entrants(names: list[str] | tuple[str, ...], track: Track, obstacles: bool) -> list[Entrant]:
    """Several policies with unique display names (a repeated name gets #2, #3, ...)."""
    if not names:
        raise PolicyError("no policy given")
    out: list[Entrant] = []
    seen: dict[str, int] = {}
    for n in names:
        e = load_entrant(n, track, obstacles)
        seen[e.name] = seen.get(e.name, 0) + 1
        if seen[e.name] > 1:
            e = Entrant(f"{e.name}#{seen[e.name]}", e.path, e.policy, e.layout)
        out.append(e)
    return out


def common_profile(entrants: list[Entrant], override: str | None = None) -> DroneProfile:
    """The drone profile the policies were trained for (all must agree), or ``override``."""
    if override is not None:
        return load_profile(override)
    names = sorted({e.meta["drone_profile"] for e in entrants})
    if len(names) > 1:
        which = ", ".join(f"{e.name}: {e.meta['drone_profile']}" for e in entrants)
        raise PolicyError(f"the policies were trained for different drone profiles ({which}); "
                          f"pass --profile to race them on one")
    return load_profile(names[0])


def load_race_track(name_or_path: str, obstacles: bool) -> Track:
    """The track, refusing --obstacles on a track without obstacles."""
    track = load_track(name_or_path)
    if obstacles and not track.obstacles:
        raise ConfigError(f"track {track.name} ({track.source}) has no obstacles; drop --obstacles")
    return track
