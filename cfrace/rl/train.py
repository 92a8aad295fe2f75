"""The training loop behind `cfrace train`: budgets, checkpoints, resume, logs, Ctrl-C.

out/checkpoint.pt   models, optimizers, normalisers, RNG states, env state, iteration, env steps,
                    config and the export metadata (written atomically every few minutes and at the end)
out/metrics.csv     one row per iteration;  out/tb/  TensorBoard scalars
out/training_curve.png   episode return per drone against env steps
"""

from __future__ import annotations

import math
import os
import signal
import threading
import time
from dataclasses import asdict, dataclass, fields, replace
from pathlib import Path
from typing import Callable

import torch

from cfrace import __version__
from cfrace.contract import MULTI_AGENT_METHODS
from cfrace.drone import DEFAULT_PROFILE
from cfrace.contract.actions import action_map_constants
from cfrace.contract.observations import DEFAULT_OPPONENT_RULE
from cfrace.errors import ConfigError
from cfrace.rl.checkpoint import CHECKPOINT, FORMAT, load_checkpoint
from cfrace.rl.config import IPPOConfig, preset
from cfrace.rl.logs import CsvLog, TensorBoardLog, plot_training_curve
from cfrace.rl.precision import Precision, resolve_precision
from cfrace.rl.runner import Runner
from cfrace.track import obstacle_scale


@dataclass(frozen=True)
class TrainConfig:
    method: str                     #: ours | ds | ss | dm
    track: str                      #: track name or YAML path
    obstacles: bool = False         #: train with the track's obstacles
    preset: str = "cpu"             #: IPPO preset (cpu | paper)
    num_envs: int | None = None     #: parallel worlds; None = the preset's
    seed: int = 0
    device: str | None = None       #: cpu | cuda; None = cuda when available
    profile: str = DEFAULT_PROFILE  #: drone profile name or path
    minutes: float | None = None    #: wall-clock budget of this run (min)
    steps: int | None = None        #: total env-step budget (world transitions, counted across resumes)
    out: str = "runs/train"         #: output folder
    checkpoint_every_s: float = 300.0  #: s between periodic checkpoints
    episode_s: float = 30.0         #: s, race length before truncation
    threads: int | None = None      #: torch intra-op threads; None = 1 on a CPU (see docs/training.md)
    overrides: tuple = ()           #: ((IPPOConfig field, value), ...) applied over the preset
    init_from: str | None = None    #: warm-start every actor from this checkpoint (see cfrace/rl/warmstart.py)
    critic_warmup: int = 20         #: iterations with frozen actors after a warm start (critics catch up)
    critic_warmup_lr: float = 1e-3  #: learning rate of those iterations (only the critics train)
    random_phase: bool = False      #: spread the first races over the time limit (RaceEnv.random_phase)
    flight_obs: bool = False        #: the flight stack's velocity estimate and thrust floor (RaceEnv.flight_obs)
    init_critic: bool = False       #: also copy the source's critic (same layout, sizes and reward only)
    fixed_opponent: str | None = None  #: checkpoint/run flying the last slot(s) in some worlds (A,B: one per world)
    fixed_opponent_frac: float = 0.5   #: share of the worlds with that fixed opponent
    fixed_opponent_drones: int = 1     #: how many drones (the last slots) it flies in those worlds
    precision: str = "auto"         #: of the PPO update: auto | fp32 | bf16 (cfrace/rl/precision.py)
    update_workers: int = 1         #: threads the agents' PPO updates run in (Runner._update; same weights)
    compile: bool = False           #: the update's forward pass and losses through torch.compile
    ground_start_prob: float | None = None  #: share of races started on the floor; None = the track's
    keep_checkpoints: bool = False  #: also keep each periodic checkpoint as checkpoints/it{N}.pt (for choosing one)
    drones: int | None = None       #: drones per world (multi-agent methods); None = 2
    opponent_rule: str = DEFAULT_OPPONENT_RULE  #: which drone each one observes when drones > 2
    obstacle_curriculum: int = 0    #: iterations over which the obstacles grow to full size (0: full from the start)
    rewards: tuple = ()             #: ((RewardScales field, value), ...) over the paper's reward weights (--reward)
    loop: dict | None = None        #: the lab's loop in training: cfrace.loopmodel.LoopRanges fields (--lab-loop)
    span_profiles: tuple = ()       #: drone-model randomisation spanning these profiles too (--span-profiles)
    parked_opponent_frac: float = 0.0  #: share of the races whose last drone starts parked (RaceEnv.parked_frac)

    def ippo(self) -> IPPOConfig:
        return preset(self.preset, self.method in MULTI_AGENT_METHODS, tuple(map(tuple, self.overrides)),
                      num_envs=self.num_envs)


@dataclass
class TrainResult:
    out: Path
    checkpoint: Path
    curve: Path | None
    iterations: int
    env_steps: int
    wall_s: float
    interrupted: bool
    exact_resume: bool | None
    last: dict
    precision: Precision | None = None


def pick_device(device: str | None) -> torch.device:
    if device is None:
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    if device not in ("cpu", "cuda") and not device.startswith("cuda:"):
        raise ConfigError(f"unknown device {device!r} (cpu or cuda)")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ConfigError("--device cuda requested but no CUDA device is available")
    return torch.device(device)


def set_threads(threads: int | None, device: torch.device) -> int:
    """One intra-op thread by default on CPU: on a shared 2-core machine more threads spin against
    the simulator and other processes (measured 10x slower updates, docs/training.md)."""
    n = threads if threads is not None else 1
    torch.set_num_threads(max(1, n))
    return torch.get_num_threads()


def make_env(cfg: TrainConfig, device: torch.device, num_envs: int):
    """The RaceEnv of this config, plus the export metadata that describes it."""
    from cfrace.env.race_env import RaceEnv
    from cfrace.env.rewards import reward_scales
    from cfrace.rl.inputs import check_inputs
    track, profile = check_inputs(cfg, sources=False)
    from cfrace.loopmodel import training_ranges
    loop, drone = training_ranges(cfg.loop, cfg.span_profiles, profile)
    if cfg.ground_start_prob is not None:  # a curriculum knob: same track, another start mix
        track = replace(track, spawn=replace(track.spawn, ground_start_prob=cfg.ground_start_prob))
    env = RaceEnv(track, profile, num_envs=num_envs, method=cfg.method, obstacles=cfg.obstacles,
                  device=str(device), seed=cfg.seed, randomize=True, episode_s=cfg.episode_s,
                  random_phase=cfg.random_phase, flight_obs=cfg.flight_obs, drones=cfg.drones,
                  opponent_rule=cfg.opponent_rule, rewards=reward_scales(cfg.rewards), loop=loop, drone=drone,
                  parked_frac=cfg.parked_opponent_frac)
    return env, env_meta(cfg, env, track.name, profile)


def env_meta(cfg: TrainConfig, env, track_name: str, profile) -> dict:
    layout = getattr(env, "layout", None)
    obstacles = bool(getattr(env, "obstacles", cfg.obstacles))  # RaceEnv drops obstacles a track does not have
    return {"method": cfg.method, "track": track_name, "obstacles": obstacles,
            "obs_layout": layout.name if layout is not None else None, "obs_dim": int(env.obs_dim),
            **action_map_constants(profile), "policy_hz": 50.0, "drone_profile": profile.name, "seed": int(cfg.seed),
            "critic_dim": int(env.critic_dim), "num_agents": int(env.num_agents),
            "flight_obs": bool(getattr(env, "flight_obs", False)),
            **({"opponent_rule": getattr(env, "opponent_rule", cfg.opponent_rule)} if int(env.num_agents) > 2 else {}),
            **({"ground_start_prob": cfg.ground_start_prob} if cfg.ground_start_prob is not None else {}),
            **({"parked_opponent_frac": float(cfg.parked_opponent_frac)} if cfg.parked_opponent_frac else {}),
            **({"obstacle_curriculum": int(cfg.obstacle_curriculum)} if cfg.obstacle_curriculum else {}),
            **({"rewards": {str(k): float(v) for k, v in cfg.rewards}} if cfg.rewards else {}),
            **({"loop": env.loop.to_meta()} if getattr(env, "loop", None) is not None else {}),
            **({"drone_ranges": env.drone.to_meta()} if getattr(env, "drone", None) is not None else {})}


def resume_config(resume: str | Path, **given) -> TrainConfig:
    """The saved TrainConfig with this run's budget/output/device; settings that define the task
    (method, track, obstacles, preset, seed, profile, envs) must match if given."""
    saved = load_checkpoint(resume)["train_config"]
    for key in ("method", "track", "obstacles", "preset", "num_envs", "seed", "profile"):
        if given.get(key) is not None and given[key] != saved[key]:
            raise ConfigError(f"--resume {resume}: {key} is {saved[key]!r} in the checkpoint, not {given[key]!r}")
    names = {f.name for f in fields(TrainConfig)}
    keep = {k: v for k, v in saved.items() if k in names}
    keep.update({k: tuple(tuple(p) for p in keep.get(k, ())) for k in ("overrides", "rewards")})
    for key in ("minutes", "steps", "device", "threads", "checkpoint_every_s"):
        keep[key] = given.get(key)
    if given.get("precision") is not None:  # how the update computes, not what the task is
        keep["precision"] = given["precision"]
    keep["update_workers"] = given.get("update_workers") or 1  # how, not what: not taken from the checkpoint
    keep["compile"] = bool(given.get("compile"))
    if given.get("keep_checkpoints"):  # a resumed run may start keeping its checkpoints
        keep["keep_checkpoints"] = True
    keep["out"] = str(given.get("out") or resume)
    if keep["checkpoint_every_s"] is None:
        keep["checkpoint_every_s"] = saved.get("checkpoint_every_s", 300.0)
    return TrainConfig(**keep)


def _save(path: Path, cfg: TrainConfig, meta: dict, runner: Runner, wall_s: float) -> None:
    state = {"format": FORMAT, "cfrace_version": __version__, "train_config": asdict(cfg), "meta": meta,
             "runner": runner.state_dict(), "wall_s": wall_s, "saved_at": time.time(),
             "precision": runner.precision.to_dict()}
    tmp = path.with_suffix(".pt.tmp")
    torch.save(state, tmp)
    os.replace(tmp, path)
    if cfg.keep_checkpoints:  # a history to choose from on validation races (hard link: no extra disk)
        keep = path.parent / "checkpoints" / f"it{runner.iteration:05d}.pt"
        keep.parent.mkdir(exist_ok=True)
        if not keep.exists():
            os.link(path, keep)


class _StopFlag:
    """First Ctrl-C (or SIGTERM): finish the iteration, checkpoint, exit. Second: stop now."""

    def __init__(self):
        self.stop = False
        self._old = {}

    def __enter__(self):
        if threading.current_thread() is threading.main_thread():
            for sig in (signal.SIGINT, signal.SIGTERM):
                self._old[sig] = signal.signal(sig, self._handle)
        return self

    def _handle(self, signum, frame):
        if self.stop:
            raise KeyboardInterrupt
        self.stop = True

    def __exit__(self, *exc):
        for sig, old in self._old.items():
            signal.signal(sig, old)


def train(cfg: TrainConfig, resume: str | Path | None = None, env_factory: Callable | None = None,
          on_iteration: Callable[[dict, dict], None] | None = None) -> TrainResult:
    """Train until the budget (minutes and/or steps) is spent or Ctrl-C; checkpoint and plot.

    env_factory(cfg, device, num_envs) -> (env, meta) replaces RaceEnv (tests use the toy env).
    on_iteration(metrics, info) is called after every iteration (info: progress 0..1, elapsed_s).
    """
    if cfg.minutes is None and cfg.steps is None:
        raise ConfigError("give a budget: --minutes M and/or --steps N")
    run = _start_run(cfg, resume, env_factory)
    runner, meta = run.runner, run.meta
    csv_log = CsvLog(run.out / "metrics.csv", resume_iteration=runner.iteration if run.resumed else None)
    tb = TensorBoardLog(run.out / "tb", purge_step=runner.iteration + 1 if run.resumed else None)
    title = f"{cfg.method} on {meta['track']}{' with obstacles' if cfg.obstacles else ''} ({runner.cfg.preset} preset)"
    run.start = time.perf_counter()
    try:
        with _StopFlag() as flag:
            metrics = _loop(run, csv_log, tb, flag, on_iteration)
            interrupted = flag.stop
        run.save(tb)
    finally:
        tb.close()
    curve = plot_training_curve(csv_log.rows, run.out / "training_curve.png", title, runner.num_agents)
    return TrainResult(run.out, run.out / CHECKPOINT, curve, runner.iteration, runner.env_steps, run.wall_s(), interrupted,
                       run.exact, metrics, runner.precision)


@dataclass
class _Run:
    """A training run between its start and its end: the runner, what is saved with it, the budget."""
    cfg: TrainConfig
    runner: Runner
    meta: dict                   #: export metadata
    info: dict                   #: what on_iteration is told besides progress
    out: Path
    resumed: bool
    exact: bool | None           #: the env's state restored too (resume only)
    wall_before: float = 0.0     #: s of training before this process (resume)
    start: float = 0.0           #: perf_counter at the first iteration

    def wall_s(self) -> float:
        return self.wall_before + time.perf_counter() - self.start

    def progress(self) -> float:
        """0..1: the larger of the spent shares of the wall-clock and env-step budgets."""
        parts = []
        if self.cfg.minutes is not None:
            parts.append((time.perf_counter() - self.start) / (60.0 * self.cfg.minutes))
        if self.cfg.steps is not None:
            parts.append(self.runner.env_steps / max(self.cfg.steps, 1))
        return min(1.0, max(parts))

    def save(self, tb: TensorBoardLog) -> None:
        _save(self.out / CHECKPOINT, self.cfg, self.meta, self.runner, self.wall_s())
        tb.flush()


def _start_run(cfg: TrainConfig, resume: str | Path | None, env_factory: Callable | None) -> _Run:
    """Device, threads, env, runner and its precision; then the resumed state, or a warm start; the
    fixed opponent."""
    device = pick_device(cfg.device)
    threads = set_threads(cfg.threads, device)
    ippo = cfg.ippo()
    out = Path(cfg.out)
    out.mkdir(parents=True, exist_ok=True)
    saved = load_checkpoint(resume) if resume is not None else None
    if saved is not None:
        ippo = IPPOConfig.from_dict(saved["runner"]["ippo"])
    env, meta = (env_factory or make_env)(cfg, device, ippo.num_envs)
    runner = Runner(env, ippo, seed=cfg.seed)
    runner.precision = resolve_precision(cfg.precision, runner)
    runner.update_workers = cfg.update_workers
    runner.use_compile(cfg.compile)
    exact, wall_before = None, 0.0
    if saved is not None and cfg.fixed_opponent:  # before the restore: building the frozen actors draws random numbers
        meta.update(_fixed_opponent(runner, cfg, meta.get("obs_layout")))
    if saved is not None:
        exact, wall_before = runner.load_state_dict(saved["runner"]), float(saved.get("wall_s", 0.0))
        meta.update({k: v for k, v in saved.get("meta", {}).items() if k.startswith("init_")})
    elif cfg.init_from:
        from cfrace.rl.warmstart import warm_start
        meta.update(warm_start(runner, cfg.init_from, meta.get("obs_layout"), critic=cfg.init_critic))
    if saved is None and cfg.fixed_opponent:
        meta.update(_fixed_opponent(runner, cfg, meta.get("obs_layout")))
    # After a warm start the actors keep the observation statistics they were trained with: updating
    # them from the new task's rollouts shifts every input of a frozen or slowly moving actor (measured:
    # a warm ours run with lr 1e-12 went from 100 % to 58 % single-agent success in 100 iterations).
    runner.update_actor_norm = not cfg.init_from
    info = {"threads": threads, "device": str(device), "num_envs": ippo.num_envs, "ippo": ippo, "meta": meta,
            "precision": runner.precision}
    return _Run(cfg, runner, meta, info, out, saved is not None, exact, wall_before)


def _loop(run: _Run, csv_log: CsvLog, tb: TensorBoardLog, flag: _StopFlag,
          on_iteration: Callable[[dict, dict], None] | None) -> dict:
    """Iterate until the budget is spent or the flag stops; log every iteration, checkpoint
    periodically. Returns the last iteration's metrics."""
    cfg, runner = run.cfg, run.runner
    metrics: dict = {}
    last_ckpt = run.start
    while run.progress() < 1.0 and not flag.stop:
        if cfg.init_from:
            _critic_warmup(runner, cfg)
        if cfg.obstacle_curriculum:  # the obstacles' size in this iteration (logged as stat_obstacle_scale)
            runner.env.set_obstacle_scale(obstacle_scale(runner.iteration, cfg.obstacle_curriculum))
        metrics = runner.iterate()
        metrics["wall_s"] = run.wall_s()
        csv_log.write(metrics)
        tb.write(metrics, runner.env_steps)
        if on_iteration is not None:
            on_iteration(metrics, {**run.info, "progress": run.progress(),
                                   "elapsed_s": time.perf_counter() - run.start})
        if time.perf_counter() - last_ckpt >= cfg.checkpoint_every_s:
            run.save(tb)
            last_ckpt = time.perf_counter()
    return metrics


def _critic_warmup(runner: Runner, cfg: TrainConfig) -> None:
    """After a warm start, train only the fresh critics at first (cfg.critic_warmup iterations)."""
    freeze = runner.iteration < cfg.critic_warmup
    for agent in runner.agents:
        agent.actor.requires_grad_(not freeze)
    # a fresh critic must reach returns of 10..500 before its advantages mean anything:
    # at the preset's rate it had not after 20 iterations (value loss 400-2400 against
    # 3-70 for the source run's own critic) and the actors, trained on those advantages,
    # forgot how to fly (docs/training.md). So the warm-up runs at its own, higher rate.
    if freeze:
        runner.set_lr(cfg.critic_warmup_lr)
    elif runner.iteration == cfg.critic_warmup:
        runner.set_lr(runner.cfg.lr)


def _fixed_opponent(runner: Runner, cfg: TrainConfig, layout: str | None) -> dict:
    """The best actors of cfg.fixed_opponent (A,B; padded like a warm start) fly the last slots (Runner.set_fixed_opponent)."""
    import types

    from cfrace.rl.models import AgentModels
    from cfrace.rl.warmstart import warm_start

    from cfrace.rl.inputs import check_fixed_opponent

    check_fixed_opponent(cfg, runner.num_agents)
    env, k, sources = runner.env, cfg.fixed_opponent_drones, [x.strip() for x in cfg.fixed_opponent.split(",")]
    opps = [AgentModels(env.obs_dim, env.critic_dim, runner.cfg.actor_hidden, runner.cfg.critic_hidden, 1.0) for _ in sources]
    names = [warm_start(types.SimpleNamespace(agents=[o], env=env), x, layout)["init_from"] for o, x in zip(opps, sources)]
    n = runner.set_fixed_opponent(opps, cfg.fixed_opponent_frac, k)
    return {"fixed_opponent": ",".join(names), "fixed_opponent_worlds": n} | ({"fixed_opponent_drones": k} if k > 1 else {})


def bench_train(method: str = "ours", track: str = "complex", obstacles: bool = False, preset_name: str = "cpu",
                num_envs: int | None = None, iterations: int = 3, device: str | None = None,
                threads: int | None = None, env_factory: Callable | None = None, overrides: tuple = (),
                precision: str = "auto", drones: int | None = None, update_workers: int = 1,
                compile: bool = False) -> dict:
    """Env-steps/s of whole training iterations, split into simulation (env.step), policy inference
    and the update. One warm-up iteration is not counted."""
    cfg = TrainConfig(method, track, obstacles, preset_name, num_envs, device=device, threads=threads, minutes=1,
                      overrides=tuple(overrides), drones=drones)
    dev = pick_device(device)
    n_threads = set_threads(threads, dev)
    ippo = cfg.ippo()
    t0 = time.perf_counter()
    env, meta = (env_factory or make_env)(cfg, dev, ippo.num_envs)
    runner = Runner(env, ippo, seed=0)
    runner.precision = resolve_precision(precision, runner)
    runner.update_workers = update_workers
    runner.use_compile(compile)
    setup_s = time.perf_counter() - t0
    warmup_s = runner.iterate()["iter_s"]  # with --compile: includes the compilation
    sums = {"iter_s": 0.0, "sim_s": 0.0, "infer_s": 0.0, "update_s": 0.0}
    cpu0 = time.process_time()
    for _ in range(iterations):
        m = runner.iterate()
        for k in sums:
            sums[k] += m[k]
    cpu_s = time.process_time() - cpu0  # the process's CPU time: what other processes on the machine don't change
    steps = iterations * ippo.rollout * ippo.num_envs
    drones = steps * runner.num_agents
    return {"method": method, "track": meta["track"], "obstacles": obstacles, "preset": ippo.preset,
            "device": str(dev), "threads": n_threads, "num_envs": ippo.num_envs, "rollout": ippo.rollout,
            "num_agents": runner.num_agents, "shared": runner.shared, "actor_hidden": list(ippo.actor_hidden),
            "critic_hidden": list(ippo.critic_hidden), "epochs": ippo.epochs, "minibatches": ippo.minibatches,
            "iterations": iterations, "setup_s": setup_s, "warmup_s": warmup_s, "compile": compile,
            "env_steps_per_s": steps / sums["iter_s"], "drone_steps_per_s": drones / sums["iter_s"],
            "env_steps_per_cpu_s": steps / cpu_s if cpu_s > 0 else math.inf,
            "sim_env_steps_per_s": steps / sums["sim_s"] if sums["sim_s"] > 0 else math.inf,
            "iteration_s": sums["iter_s"] / iterations,
            "share_sim": sums["sim_s"] / sums["iter_s"], "share_inference": sums["infer_s"] / sums["iter_s"],
            "share_update": sums["update_s"] / sums["iter_s"],
            "share_other": 1.0 - (sums["sim_s"] + sums["infer_s"] + sums["update_s"]) / sums["iter_s"],
            "precision": runner.precision.to_dict(), "update_workers": update_workers}
