"""`cfrace train`'s options as data: the parameters typer reads (train_parameters), the TrainConfig
they make (checked_config) and the check `cfrace sweep` runs on a run's argument list (check_train_argv).

cfrace.cli.train builds the command from train_parameters and cfrace.sweep.spec reads the same
signature for the keys a sweep run accepts, so the command and the sweep format cannot drift apart.
Light at import (typer only): every `cfrace` command line imports it.
"""

from __future__ import annotations

import inspect
import typing
from pathlib import Path
from typing import Optional

import typer

#: options of both `train` and `bench train`
UPDATE_WORKERS = typer.Option(1, "--update-workers", min=1,
                              help="threads the agents' PPO updates run in at once (one agent per thread; "
                                   "the same weights as one after the other)")
COMPILE = typer.Option(False, "--compile/--no-compile",
                       help="the update's forward pass and losses through torch.compile (compiles for tens "
                            "of seconds at the start)")


def train_parameters(
    method: Optional[str] = typer.Option(None, "--method", help="ours | ds | ss | dm (required unless --resume)"),
    track: Optional[str] = typer.Option(None, "--track", help="track name or YAML path (required unless --resume)"),
    obstacles: Optional[bool] = typer.Option(None, "--obstacles/--no-obstacles", help="train with obstacles"),
    preset: Optional[str] = typer.Option(None, "--preset", help="cpu (default) | paper"),
    envs: Optional[int] = typer.Option(None, "--envs", min=1, help="parallel worlds (default: the preset's)"),
    minutes: Optional[float] = typer.Option(None, "--minutes", min=0.0, help="wall-clock budget of this run"),
    steps: Optional[int] = typer.Option(None, "--steps", min=1, help="total env-step budget (world transitions)"),
    seed: Optional[int] = typer.Option(None, "--seed", help="random seed (default 0)"),
    out: Optional[Path] = typer.Option(None, "--out", help="output folder (default runs/METHOD_TRACK[_obstacles]_sSEED)"),
    resume: Optional[Path] = typer.Option(None, "--resume", help="continue the run in this folder from its checkpoint"),
    device: Optional[str] = typer.Option(None, "--device", help="cpu | cuda (default: cuda when available)"),
    profile: Optional[str] = typer.Option(None, "--profile", help="drone profile (default cf2x_paper)"),
    threads: Optional[int] = typer.Option(None, "--threads", min=1, help="torch threads (default 1 on CPU)"),
    checkpoint_min: Optional[float] = typer.Option(None, "--checkpoint-min", min=0.0,
                                                   help="minutes between checkpoints (default 5; a resumed run: its own)"),
    set_: Optional[list[str]] = typer.Option(None, "--set", help="override a preset field, e.g. --set epochs=3"),
    reward: Optional[list[str]] = typer.Option(None, "--reward", help="override a reward weight, e.g. --reward gate=10 "
                                               "(cfrace.env.rewards.RewardScales; recorded in the policy)"),
    init_from: Optional[Path] = typer.Option(None, "--init-from",
                                             help="warm-start every actor from this checkpoint or run folder"),
    episode_s: float = typer.Option(30.0, "--episode-s", min=1.0, help="race length before the time-out (s)"),
    critic_warmup: int = typer.Option(20, "--critic-warmup", min=0,
                                      help="iterations with frozen actors after --init-from"),
    random_phase: bool = typer.Option(False, "--random-phase",
                                      help="first races start part-way into the time limit (spread time-outs)"),
    fixed_opponent: Optional[Path] = typer.Option(None, "--fixed-opponent",
                                                  help="checkpoint or run whose actor (frozen) flies the "
                                                       "second drone in part of the worlds (several: A,B: "
                                                       "one per world, in turn)"),
    fixed_opponent_frac: float = typer.Option(0.5, "--fixed-opponent-frac",
                                              help="share of the worlds with the fixed opponent"),
    fixed_opponent_drones: int = typer.Option(1, "--fixed-opponent-drones", min=1,
                                              help="drones it flies in those worlds (the last slots)"),
    init_critic: bool = typer.Option(False, "--init-critic",
                                     help="with --init-from: copy the critic too (same layout, sizes, reward)"),
    critic_warmup_lr: float = typer.Option(1e-3, "--critic-warmup-lr", min=0.0,
                                           help="learning rate of the critic warm-up iterations"),
    precision: Optional[str] = typer.Option(None, "--precision",
                                            help="PPO update in auto (measured at start, default) | fp32 | bf16"),
    ground_start_prob: Optional[float] = typer.Option(None, "--ground-start-prob",
                                                      help="share of training races started on the floor "
                                                           "(default: the track's spawn.ground_start_prob)"),
    keep_checkpoints: bool = typer.Option(False, "--keep-checkpoints",
                                          help="keep every periodic checkpoint as OUT/checkpoints/itN.pt"),
    drones: Optional[int] = typer.Option(None, "--drones", min=2,
                                         help="drones per world for ours / dm (default 2): an N-drone race"),
    opponent_rule: Optional[str] = typer.Option(None, "--opponent-rule",
                                                help="with --drones > 2: which drone each one observes: "
                                                     "nearest (default) | ahead | track"),
    obstacle_curriculum: int = typer.Option(0, "--obstacle-curriculum", min=0,
                                            help="with --obstacles: the obstacles grow from nothing to full size "
                                                 "over the first ITERS iterations (0: full size throughout)"),
    update_workers: int = UPDATE_WORKERS,
    compile_: bool = COMPILE,
    flight_obs: bool = typer.Option(False, "--flight-obs",
                                    help="observe velocity as the flight stack estimates it (10-ms pose "
                                         "difference) and keep thrust above the firmware's least command"),
    lab_loop: bool = typer.Option(False, "--lab-loop",
                                  help="train through a lab's loop (cfrace.loopmodel; implies --flight-obs): "
                                       "pose age, jitter, mocap noise, dropped frames, late setpoints, the "
                                       "estimator's forward prediction in part of the episodes"),
    loop_latency_ms: Optional[str] = typer.Option(None, "--loop-latency-ms", metavar="LO,HI",
                                                  help="with --lab-loop: per-episode pose age range, ms (default 0,30)"),
    loop_noise_mm: Optional[str] = typer.Option(None, "--loop-noise-mm", metavar="LO,HI",
                                                help="with --lab-loop: per-episode mocap position noise std range, "
                                                     "mm (default 0.5,3)"),
    span_profiles: Optional[str] = typer.Option(None, "--span-profiles", metavar="A,B",
                                                help="randomise the drone model to span these drone profiles "
                                                     "as well as --profile (e.g. cf21bl): thrust, motor time "
                                                     "constant, thrust limit and idle, drag, rate gains"),
    parked_opponent_frac: float = typer.Option(0.0, "--parked-opponent-frac",
                                               help="share of the races whose last drone starts crashed on the "
                                                    "floor below its start slot: the others race nobody, as a "
                                                    "policy flying alone does (default 0)"),
) -> dict:
    """`cfrace train`'s options by parameter name (the signature is what counts: see takes_train_options)."""
    return dict(locals())


def takes_train_options(command):
    """``command(**options)`` with train_parameters' signature and types, as typer and the sweep read them."""
    command.__signature__ = inspect.signature(train_parameters, eval_str=True).replace(return_annotation=None)
    command.__annotations__ = {**typing.get_type_hints(train_parameters), "return": None}
    return command


def checked_config(*, method, track, obstacles, preset, envs, minutes, steps, seed, out, resume, device, profile,
                   threads, checkpoint_min, set_, reward, init_from, episode_s, critic_warmup, random_phase,
                   fixed_opponent, fixed_opponent_frac, fixed_opponent_drones, init_critic, critic_warmup_lr,
                   precision, ground_start_prob, keep_checkpoints, drones, opponent_rule, obstacle_curriculum,
                   update_workers, compile_, flight_obs, lab_loop=False, loop_latency_ms=None, loop_noise_mm=None,
                   span_profiles=None, parked_opponent_frac=0.0, sources: bool = True):
    """The TrainConfig of `cfrace train`'s options (its parameters), checked as the command checks it
    before its banner (cfrace.rl.inputs.check_inputs; ``sources``: also load the files it names);
    ConfigError (one line) else. `cfrace sweep` checks its runs with it (check_train_argv)."""
    from cfrace.errors import ConfigError
    from cfrace.rl.config import parse_overrides
    if resume is None and (method is None or track is None):   # before any heavy import
        raise ConfigError("--method and --track are required (or --resume DIR)")
    overrides = parse_overrides(set_ or [])
    from cfrace.env.rewards import parse_reward_overrides
    rewards = parse_reward_overrides(reward or [])
    from cfrace.rl.train import TrainConfig, resume_config

    if minutes is None and steps is None:
        minutes = 30.0
    if resume is not None:
        if overrides or rewards:
            raise ConfigError("--set and --reward cannot change a resumed run")
        cfg = resume_config(resume, method=method, track=track, obstacles=obstacles, preset=preset, num_envs=envs,
                            seed=seed, profile=profile, minutes=minutes, steps=steps, device=device, threads=threads,
                            out=str(out) if out else None,
                            checkpoint_every_s=None if checkpoint_min is None else checkpoint_min * 60.0,
                            precision=precision, keep_checkpoints=keep_checkpoints, update_workers=update_workers,
                            compile=compile_)
    else:
        seed = 0 if seed is None else seed
        name = f"{method}_{Path(track).stem}{'_obstacles' if obstacles else ''}_s{seed}"
        cfg = TrainConfig(method, track, bool(obstacles), preset or "cpu", envs, seed, device,
                          profile or TrainConfig.profile, minutes, steps, str(out or Path("runs") / name),
                          (5.0 if checkpoint_min is None else checkpoint_min) * 60.0, threads=threads, overrides=overrides,
                          init_from=str(init_from) if init_from else None, critic_warmup=critic_warmup,
                          critic_warmup_lr=critic_warmup_lr, episode_s=episode_s,
                          init_critic=init_critic, random_phase=random_phase,
                          fixed_opponent=str(fixed_opponent) if fixed_opponent else None,
                          fixed_opponent_frac=fixed_opponent_frac,
                          fixed_opponent_drones=fixed_opponent_drones, flight_obs=flight_obs,
                          keep_checkpoints=keep_checkpoints, precision=precision or "auto",
                          ground_start_prob=ground_start_prob, drones=drones,
                          update_workers=update_workers, compile=compile_,
                          opponent_rule=opponent_rule or TrainConfig.opponent_rule,
                          obstacle_curriculum=obstacle_curriculum, rewards=rewards,
                          loop=loop_ranges(lab_loop, loop_latency_ms, loop_noise_mm),
                          span_profiles=tuple(x.strip() for x in (span_profiles or "").split(",") if x.strip()),
                          parked_opponent_frac=parked_opponent_frac)
    from cfrace.rl.inputs import check_inputs
    check_inputs(cfg, sources=sources, warm_start=resume is None)
    return cfg


def check_train_argv(argv: list[str]) -> None:
    """What `cfrace train ARGV` (ARGV without "train") refuses before its banner, without running it:
    the options parsed as the command parses them (types, ranges), then checked_config without
    loading the files they name (a sweep's references may not exist yet); ConfigError (one line)."""
    from typer.main import get_command

    from cfrace.errors import ConfigError
    try:
        from typer._click.exceptions import ClickException   # typer >= 0.2x carries its own click
    except ImportError:                                      # older typer: click itself
        from click.exceptions import ClickException

    app = typer.Typer()
    app.command()(train_parameters)
    try:
        ctx = get_command(app).make_context("train", list(argv))
    except ClickException as exc:
        raise ConfigError(exc.format_message()) from None
    checked_config(**ctx.params, sources=False)


def _range_option(option: str, text: str, unit: float, hi: float) -> tuple[float, float]:
    """'LO,HI' in the option's unit -> (lo, hi) in SI; ConfigError naming the option."""
    from cfrace.errors import ConfigError
    from cfrace.loopmodel import _range
    parts = text.split(",")
    try:
        values = [float(p) for p in parts]
    except ValueError:
        raise ConfigError(f"{option}: two numbers LO,HI, got {text!r}") from None
    if len(values) != 2:
        raise ConfigError(f"{option}: two numbers LO,HI, got {text!r}")
    lo, hi_ = _range(option, values, 0.0, hi)
    return lo * unit, hi_ * unit


def loop_ranges(lab_loop: bool, latency_ms: str | None, noise_mm: str | None) -> dict | None:
    """--lab-loop and its ranges -> TrainConfig.loop (LoopRanges fields as plain data)."""
    from cfrace.errors import ConfigError
    from cfrace.loopmodel import MAX_LATENCY_S, LoopRanges
    if not lab_loop:
        if latency_ms is not None or noise_mm is not None:
            raise ConfigError("--loop-latency-ms / --loop-noise-mm: only with --lab-loop")
        return None
    given = {}
    if latency_ms is not None:
        given["latency_s"] = _range_option("--loop-latency-ms", latency_ms, 1e-3, MAX_LATENCY_S * 1e3)
    if noise_mm is not None:
        given["noise_m"] = _range_option("--loop-noise-mm", noise_mm, 1e-3, 50.0)
    return LoopRanges(**given).to_meta()
