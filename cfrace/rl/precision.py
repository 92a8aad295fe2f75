"""Mixed precision of the PPO update: bfloat16 matrix products where the CPU (or GPU) runs them
faster, float32 everywhere else.

What runs in bf16 (``torch.autocast``): the hidden layers of the actor's mean network and of the
critic inside the update, forward and backward. What stays float32: the two output layers (a bf16
value of a return in the thousands would be off by several units, as large as the advantages it
resolves: measured, DS learnt slower per sample with bf16 outputs), the weights themselves
(autocast casts a bf16 copy per use), their gradients and Adam's moments, the Gaussian's
log-probabilities and entropy, the ratios, advantages, returns, every loss term, the KL, the
observation normalisers, the rollout's inference (so the old log-probabilities are the float32
policy's) and the exported ONNX graph.

``auto`` (the default) measures: one forward + backward pass of the run's actor and critic at the
update's minibatch size, float32 against bf16, a few repetitions each (CPU time of the thread on a
CPU, so a busy machine does not tip the choice), and takes bf16 when it is at least MIN_GAIN times
faster. The choice, the measured times and the reason are returned as a
:class:`Precision` and recorded in the run (checkpoint, metrics, console).
"""

from __future__ import annotations

import contextlib
import time
from dataclasses import dataclass
from typing import Sequence

import torch

from cfrace.errors import ConfigError

MODES = ("auto", "fp32", "bf16")
MIN_GAIN = 1.15  #: auto takes bf16 only when the measured update step is at least this much faster


@dataclass(frozen=True)
class Precision:
    mode: str            #: what was asked: auto | fp32 | bf16
    dtype: str           #: what the update runs in: fp32 | bf16
    reason: str          #: one line: why
    fp32_ms: float | None = None  #: measured forward+backward per minibatch (auto only)
    bf16_ms: float | None = None

    @property
    def bf16(self) -> bool:
        return self.dtype == "bf16"

    def autocast(self, device: torch.device):
        """The context the update's forward passes run in."""
        if not self.bf16:
            return contextlib.nullcontext()
        return torch.autocast(device_type=device.type, dtype=torch.bfloat16)

    def to_dict(self) -> dict:
        return {"mode": self.mode, "dtype": self.dtype, "reason": self.reason,
                "fp32_ms": self.fp32_ms, "bf16_ms": self.bf16_ms}


def cpu_has_bf16() -> bool:
    """True when this x86 CPU has bf16 matrix instructions (AMX-BF16 or AVX512-BF16)."""
    try:
        flags = open("/proc/cpuinfo").read()
    except OSError:
        return False
    return " amx_bf16" in flags or " avx512_bf16" in flags


def _step_ms(actor: torch.nn.Module, critic: torch.nn.Module, x_a: torch.Tensor, x_c: torch.Tensor,
             ctx, reps: int) -> float:
    """Median time (ms) of one forward + backward of both networks under ``ctx``. On a CPU it is the
    thread's CPU time, so that other processes on a shared machine do not decide the choice."""
    cuda = x_a.device.type == "cuda"
    clock = time.perf_counter if cuda else time.thread_time
    times = []
    for i in range(reps + 2):
        t0 = clock()
        with ctx():
            loss = actor(x_a).float().square().mean() + critic(x_c).float().square().mean()
        loss.backward()
        if cuda:
            torch.cuda.synchronize(x_a.device)
        if i >= 2:  # two warm-up passes (oneDNN builds its kernels on first use)
            times.append(clock() - t0)
    times.sort()
    return 1e3 * times[len(times) // 2]


def check_precision(mode: str) -> None:
    """ConfigError (one line) unless ``mode`` is one of MODES (checked before `cfrace train`'s banner too)."""
    if mode not in MODES:
        raise ConfigError(f"--precision {mode!r}: choose from {', '.join(MODES)}")


def choose_precision(mode: str, device: torch.device, obs_dim: int, critic_dim: int,
                     actor_hidden: Sequence[int], critic_hidden: Sequence[int], minibatch: int,
                     reps: int = 5) -> Precision:
    """Resolve ``--precision`` for this run (see the module docstring)."""
    from cfrace.rl.models import mlp

    check_precision(mode)
    if mode == "fp32":
        return Precision("fp32", "fp32", "asked for float32")
    supported = torch.cuda.is_bf16_supported() if device.type == "cuda" else cpu_has_bf16()
    if mode == "bf16":
        note = "asked for bf16" + ("" if supported else " (this device has no bf16 matrix unit: expect it slower)")
        return Precision("bf16", "bf16", note)
    if not supported:
        return Precision("auto", "fp32", "no bf16 matrix unit on this device (AMX-BF16/AVX512-BF16 or a bf16 GPU)")
    minibatch = max(64, min(int(minibatch), 8192))  # the measurement stays well under a second
    gen = torch.Generator().manual_seed(0)
    actor = mlp(obs_dim, actor_hidden, 4).to(device)
    critic = mlp(critic_dim, critic_hidden, 1).to(device)
    x_a = torch.randn(minibatch, obs_dim, generator=gen).to(device)
    x_c = torch.randn(minibatch, critic_dim, generator=gen).to(device)
    fp32 = _step_ms(actor, critic, x_a, x_c, contextlib.nullcontext, reps)
    bf16 = _step_ms(actor, critic, x_a, x_c, lambda: torch.autocast(device_type=device.type, dtype=torch.bfloat16),
                    reps)
    gain = fp32 / bf16
    if gain >= MIN_GAIN:
        return Precision("auto", "bf16", f"bf16 update step {gain:.2f}x faster ({fp32:.1f} -> {bf16:.1f} ms "
                                         f"per minibatch of {minibatch})", fp32, bf16)
    return Precision("auto", "fp32", f"bf16 not faster enough here ({gain:.2f}x < {MIN_GAIN}x)", fp32, bf16)


def resolve_precision(mode: str, runner) -> Precision:
    """``--precision`` for a Runner's networks and minibatch size (measured when auto)."""
    ippo, env = runner.cfg, runner.env
    minibatch = ippo.num_envs * ippo.rollout // ippo.minibatches
    return choose_precision(mode, runner.device, env.obs_dim, env.critic_dim, ippo.actor_hidden,
                            ippo.critic_hidden, minibatch)
