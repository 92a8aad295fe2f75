"""What a training run is given, checked before anything is printed, made or trained: one line
(ConfigError) naming the option, as every command's bad input. `cfrace train` calls check_inputs
before its banner, and make_env (cfrace.rl.train) before it builds the environment."""

from __future__ import annotations

from numbers import Integral
from pathlib import Path

from cfrace.contract import METHODS, MULTI_AGENT_METHODS
from cfrace.drone import load_profile
from cfrace.contract.observations import OPPONENT_RULES, layout_for
from cfrace.errors import ConfigError
from cfrace.track import load_track


def check_method(method: str, where: str = "") -> None:
    """ConfigError (one line, after ``where``) unless ``method`` is one of the four schemes."""
    if method not in METHODS:
        raise ConfigError(f"{where}unknown method {method!r} (choose from {', '.join(METHODS)})")


def check_inputs(cfg, sources: bool = True, warm_start: bool = True) -> tuple:
    """(track, profile) of a TrainConfig once its method, drone count, opponent rule, worlds, episode
    length, start mix, precision and frozen-opponent share and drones hold up, and with ``sources``
    its frozen-opponent files and (``warm_start``: a new run, not a resumed one) its warm-start file
    load and fit the run (observation layout; a critic to copy; a frozen opponent trained on this
    track and obstacles setting); ConfigError (one line) else."""
    check_method(cfg.method)
    if cfg.drones is not None and (cfg.drones < 2 or cfg.method not in MULTI_AGENT_METHODS):
        raise ConfigError(f"--drones {cfg.drones}: at least 2, and only for the multi-agent methods "
                          f"({', '.join(MULTI_AGENT_METHODS)}), not {cfg.method}")
    if cfg.opponent_rule not in OPPONENT_RULES:
        raise ConfigError(f"--opponent-rule {cfg.opponent_rule!r}: one of {', '.join(OPPONENT_RULES)}")
    if cfg.num_envs is not None and (not isinstance(cfg.num_envs, Integral) or isinstance(cfg.num_envs, bool)
                                     or cfg.num_envs < 1):
        raise ConfigError(f"--envs (num_envs) must be a whole number of at least 1, got {cfg.num_envs!r}")
    if cfg.episode_s is not None and not cfg.episode_s > 0:
        raise ConfigError(f"--episode-s (episode_s) must be > 0 s, got {cfg.episode_s}")
    if cfg.ground_start_prob is not None and not 0.0 <= cfg.ground_start_prob <= 1.0:
        raise ConfigError(f"--ground-start-prob must be in [0, 1], got {cfg.ground_start_prob}")
    from cfrace.env.race_env import parked_share
    parked_share(cfg.method, getattr(cfg, "parked_opponent_frac", 0.0))
    from cfrace.rl.precision import check_precision
    from cfrace.rl.warmstart import check_source

    check_precision(cfg.precision)
    multi = cfg.method in MULTI_AGENT_METHODS
    check_fixed_opponent(cfg, (cfg.drones or 2) if multi else 1)
    track, profile = load_track(cfg.track), load_profile(cfg.profile)
    for name in getattr(cfg, "span_profiles", ()):
        try:
            load_profile(name)
        except ConfigError as exc:
            raise ConfigError(f"--span-profiles: {exc}") from None
    if getattr(cfg, "loop", None) is not None:
        from cfrace.loopmodel import LoopRanges
        LoopRanges.from_meta(cfg.loop)
    obstacles = bool(cfg.obstacles and track.obstacles)     # as RaceEnv: a track without obstacles drops them
    layout = layout_for(multi, obstacles).name
    init_from = cfg.init_from if warm_start else None
    if init_from:                                           # an exported policy has no critic to copy
        check_source(init_from, None, layout, critic=cfg.init_critic)
    files = [("--init-from", init_from)] + [("--fixed-opponent", x.strip())
                                            for x in (cfg.fixed_opponent or "").split(",") if x.strip()]
    for option, source in (files if sources else []):
        if source:
            meta = _readable(option, Path(source))
            if option == "--fixed-opponent":
                _same_race(option, Path(source), meta, track.name, obstacles)
            check_source(source, meta.get("obs_layout"), layout, option=option)
    return track, profile


def check_fixed_opponent(cfg, num_agents: int) -> None:
    """ConfigError (one line) unless the frozen opponent's share of the worlds is in (0, 1] and, with
    --fixed-opponent, the method races (``num_agents`` drones per world) with a learner left."""
    if not 0.0 < cfg.fixed_opponent_frac <= 1.0:
        raise ConfigError(f"--fixed-opponent-frac must be in (0, 1], got {cfg.fixed_opponent_frac}")
    if not cfg.fixed_opponent:
        return
    if num_agents < 2:
        raise ConfigError(f"--fixed-opponent needs a multi-agent method ({', '.join(MULTI_AGENT_METHODS)}), "
                          f"not {cfg.method}")
    check_fixed_drones(cfg.fixed_opponent_drones, num_agents)


def check_fixed_drones(drones: int, num_agents: int) -> None:
    """The frozen opponent flies 1 to N - 1 of the N drones of a world (Runner.set_fixed_opponent)."""
    if not 1 <= drones < num_agents:
        raise ConfigError(f"--fixed-opponent-drones {drones}: from 1 to {num_agents - 1} with "
                          f"{num_agents} drones per world (at least one must learn)")


def _same_race(option: str, path: Path, meta: dict, track_name: str, obstacles: bool) -> None:
    """A frozen opponent races here as it was trained: on this track, with this obstacles setting.
    The rule is the flight stack's (OnnxPolicy.check), applied to a checkpoint's metadata too."""
    from types import SimpleNamespace

    from cfrace.errors import PolicyError
    from cfrace.policy import OnnxPolicy

    try:
        OnnxPolicy.check(SimpleNamespace(meta=meta, path=path), track_name, obstacles)
    except PolicyError as exc:
        raise ConfigError(f"{option} {exc}") from None


def _readable(option: str, path: Path) -> dict:
    """The metadata (obs_layout, track, obstacles, ...) of a run folder, a checkpoint or an exported
    .onnx policy that loads (warm_start reads it later)."""
    from cfrace.rl.checkpoint import load_checkpoint

    if path.suffix == ".onnx":
        from cfrace.errors import PolicyError
        from cfrace.policy import OnnxPolicy
        try:
            return OnnxPolicy(path).meta
        except PolicyError as exc:
            raise ConfigError(f"{option} {exc}") from None
    try:
        return load_checkpoint(path).get("meta", {})
    except ConfigError as exc:
        raise ConfigError(f"{option} {exc}") from None
