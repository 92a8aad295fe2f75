"""What a training run is given, checked before anything is printed, made or trained: one line
(ConfigError) naming the option, as every command's bad input. `cfrace train` calls check_inputs
before its banner, and make_env (cfrace.rl.train) before it builds the environment."""

from __future__ import annotations

from pathlib import Path

from cfrace.contract import METHODS, MULTI_AGENT_METHODS
from cfrace.drone import load_profile
from cfrace.env.observations import OPPONENT_RULES
from cfrace.errors import ConfigError
from cfrace.track import load_track


def check_method(method: str, where: str = "") -> None:
    """ConfigError (one line, after ``where``) unless ``method`` is one of the four schemes."""
    if method not in METHODS:
        raise ConfigError(f"{where}unknown method {method!r} (choose from {', '.join(METHODS)})")


def check_inputs(cfg, sources: bool = True, warm_start: bool = True) -> tuple:
    """(track, profile) of a TrainConfig once its method, drone count, opponent rule, worlds, episode
    length and start mix hold up, and with ``sources`` its frozen-opponent files and (``warm_start``:
    a new run, not a resumed one) its warm-start file load; ConfigError (one line) else."""
    check_method(cfg.method)
    if cfg.drones is not None and (cfg.drones < 2 or cfg.method not in MULTI_AGENT_METHODS):
        raise ConfigError(f"--drones {cfg.drones}: at least 2, and only for the multi-agent methods "
                          f"({', '.join(MULTI_AGENT_METHODS)}), not {cfg.method}")
    if cfg.opponent_rule not in OPPONENT_RULES:
        raise ConfigError(f"--opponent-rule {cfg.opponent_rule!r}: one of {', '.join(OPPONENT_RULES)}")
    if cfg.num_envs is not None and not cfg.num_envs >= 1:
        raise ConfigError(f"--envs (num_envs) must be at least 1, got {cfg.num_envs}")
    if cfg.episode_s is not None and not cfg.episode_s > 0:
        raise ConfigError(f"--episode-s (episode_s) must be > 0 s, got {cfg.episode_s}")
    if cfg.ground_start_prob is not None and not 0.0 <= cfg.ground_start_prob <= 1.0:
        raise ConfigError(f"--ground-start-prob must be in [0, 1], got {cfg.ground_start_prob}")
    track, profile = load_track(cfg.track), load_profile(cfg.profile)
    files = [("--init-from", cfg.init_from if warm_start else None)] + [("--fixed-opponent", x.strip())
                                                for x in (cfg.fixed_opponent or "").split(",") if x.strip()]
    for option, source in (files if sources else []):
        if source:
            _readable(option, Path(source))
    return track, profile


def _readable(option: str, path: Path) -> None:
    """A run folder, a checkpoint or an exported .onnx policy that loads (warm_start reads it later)."""
    from cfrace.rl.checkpoint import load_checkpoint

    if path.suffix == ".onnx":
        from cfrace.errors import PolicyError
        from cfrace.policy import OnnxPolicy
        try:
            OnnxPolicy(path)
        except PolicyError as exc:
            raise ConfigError(f"{option} {exc}") from None
        return
    try:
        load_checkpoint(path)
    except ConfigError as exc:
        raise ConfigError(f"{option} {exc}") from None
