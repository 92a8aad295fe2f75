"""IPPO hyperparameters as frozen dataclasses, with two presets.

``paper``: the authors' settings (the paper's training settings), sized for a large GPU.
``cpu``  : the default, sized by measurement for a 2-core laptop CPU (docs/training.md has the
           figures behind every choice). Both come in a multi-agent (ours, dm) and a
           single-agent (ds, ss) flavour, as in the paper.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, fields, replace

from cfrace.errors import ConfigError

PRESETS = ("cpu", "paper")


@dataclass(frozen=True)
class IPPOConfig:
    preset: str
    actor_hidden: tuple[int, ...]    #: hidden layer widths of each actor (ELU)
    critic_hidden: tuple[int, ...]   #: hidden layer widths of each critic (ELU)
    num_envs: int                    #: parallel worlds (a race with 1 or 2 drones each)
    rollout: int                     #: policy steps per world per iteration (50 Hz steps)
    epochs: int                      #: passes over each rollout
    minibatches: int                 #: minibatches per epoch
    lr: float                        #: Adam learning rate (initial when adaptive)
    desired_kl: float | None         #: adaptive LR target KL; None = fixed LR
    gamma: float                     #: discount per policy step
    lam: float                       #: GAE lambda
    clip: float                      #: PPO ratio clip
    value_clip: float | None         #: value-function clip around the old value; None = off
    entropy_coef: float              #: entropy bonus weight
    value_coef: float                #: value loss weight
    grad_clip: float                 #: max global grad norm per agent
    init_std: float = 1.0            #: initial action std (Gaussian, state-independent)
    bound_coef: float = 0.0          #: weight of the action-bound loss mean(sum(relu(|mu| - 1)^2)); 0 = off
    lr_min: float = 1e-5             #: adaptive LR bounds
    lr_max: float = 1e-2
    shared: bool = False             #: one actor + critic for every drone of a world (False: one per drone, IPPO)
    std_final: float | None = None   #: action-std cap schedule: the cap falls from init_std to this (None: no cap)
    std_anneal_iters: int = 1        #: ... over this many iterations (std_cap)

    def to_dict(self) -> dict:
        return asdict(self)

    @staticmethod
    def from_dict(data: dict) -> "IPPOConfig":
        names = {f.name for f in fields(IPPOConfig)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ConfigError(f"unknown IPPO config key(s): {', '.join(unknown)}")
        data = dict(data)
        for k in ("actor_hidden", "critic_hidden"):
            data[k] = tuple(data[k])
        return IPPOConfig(**data)


_SHARED = dict(gamma=0.99, lam=0.95, clip=0.2, value_clip=0.2, entropy_coef=0.0, value_coef=1.0, epochs=5,
               minibatches=4)

_PAPER = {
    True: IPPOConfig("paper", (512, 512, 256, 128), (512, 512, 256, 256, 128, 128), num_envs=10240, rollout=16,
                     lr=1e-4, desired_kl=None, grad_clip=0.5, **_SHARED),
    False: IPPOConfig("paper", (512, 512, 256, 128), (512, 512, 256, 256, 128, 128), num_envs=10240, rollout=24,
                      lr=5e-4, desired_kl=0.01, grad_clip=1.0, **_SHARED),
}

# CPU: smaller networks and fewer worlds; the update cost grows with the critic size times the batch,
# the simulation with the worlds. See docs/training.md for the measurements.
# Few iterations on a CPU: no value clip (the critic must follow returns of 10..5000 quickly), and an
# action-bound loss so that the mean action (what the ONNX policy outputs) stays inside [-1, 1]:
# measured, DS on complex after 3.8 M steps, the mean-action policy finishes a lap in 86 % of
# starts with it and 14 % without (docs/training.md).
_CPU_SHARED = {**_SHARED, "value_clip": None, "bound_coef": 0.1}
_CPU = {
    True: IPPOConfig("cpu", (128, 128), (256, 128), num_envs=1024, rollout=16, lr=3e-4, desired_kl=None,
                     grad_clip=0.5, **_CPU_SHARED),
    False: IPPOConfig("cpu", (128, 128), (256, 128), num_envs=1024, rollout=24, lr=5e-4, desired_kl=0.01,
                      grad_clip=1.0, **_CPU_SHARED),
}


_INTS = ("num_envs", "rollout", "epochs", "minibatches", "std_anneal_iters")
_LAYERS = ("actor_hidden", "critic_hidden")
_OPTIONAL = ("desired_kl", "value_clip", "std_final")
_BOOLS = ("shared",)


def parse_overrides(items: list[str] | tuple[str, ...]) -> tuple[tuple[str, object], ...]:
    """["epochs=3", "actor_hidden=[64, 64]", "value_clip=none", "lr=2e-4"] -> (("epochs", 3), ...),
    checked against IPPOConfig's fields and types (ConfigError naming the item otherwise)."""
    import yaml

    names = {f.name for f in fields(IPPOConfig)} - {"preset"}
    out = []
    for item in items:
        key, sep, text = item.partition("=")
        key, text = key.strip(), text.strip()
        if not sep or key not in names:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE with KEY one of {', '.join(sorted(names))}")
        try:
            if key in _OPTIONAL and text.lower() in ("none", "null", "off"):
                value = None
            elif key in _BOOLS:
                if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
                    raise ValueError
                value = text.lower() in ("true", "1", "yes")
            elif key in _INTS:
                value = int(text)
                if value < 1:
                    raise ValueError
            elif key in _LAYERS:
                raw = yaml.safe_load(text)
                if not isinstance(raw, list) or not raw or not all(isinstance(v, int) and v > 0 for v in raw):
                    raise ValueError
                value = tuple(raw)
            else:
                value = float(text)
        except (ValueError, yaml.YAMLError):
            raise ConfigError(f"--set {item!r}: bad value for {key}") from None
        out.append((key, value))
    return tuple(out)


def preset(name: str, multi_agent: bool, overrides: tuple[tuple[str, object], ...] = (), **kw) -> IPPOConfig:
    """The named preset for a multi- or single-agent method; ``kw`` fields set when not None,
    then ``overrides`` (key, value) pairs applied as given (None allowed, e.g. value_clip=None)."""
    cfg = _preset(name, multi_agent, **kw)
    try:
        return replace(cfg, **dict(overrides))
    except TypeError as exc:
        raise ConfigError(f"bad IPPO override: {exc}") from None


def _preset(name: str, multi_agent: bool, **overrides) -> IPPOConfig:
    """The named preset for a multi- or single-agent method, with fields overridden (None = keep)."""
    table = {"cpu": _CPU, "paper": _PAPER}.get(name)
    if table is None:
        raise ConfigError(f"unknown preset {name!r} (choose from {', '.join(PRESETS)})")
    overrides = {k: v for k, v in overrides.items() if v is not None}
    return replace(table[multi_agent], **overrides)


def std_cap(cfg: IPPOConfig, iteration: int) -> float | None:
    """The cap on the actors' action std in ``iteration`` (0-based): None without a schedule; else
    linear from init_std at iteration 0 to std_final at std_anneal_iters, then std_final. The
    learned std may fall below it; it never samples above it (docs/training.md, "Sparse from
    scratch")."""
    if cfg.std_final is None:
        return None
    frac = min(1.0, iteration / max(cfg.std_anneal_iters, 1))
    return cfg.init_std + (cfg.std_final - cfg.init_std) * frac
