"""PPO hyper-parameters (:class:`PPOConfig`), the activation and architecture names of ``--act``/``--arch``,
and the learning-rate schedule's factor (:func:`linear_lr_scale`; the optimizer applies it as an injected
hyper-parameter, :func:`quadswarm_mj.training.learner.make_optimizer`).

Imports flax (the activations) but no engine.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from flax import linen

from quadswarm_mj.policies import ARCH_PRESETS

ACTIVATIONS: dict[str, Callable[[Any], Any]] = {"tanh": linen.tanh, "relu": linen.relu, "swish": linen.swish,
                                                "elu": linen.elu}
#: policy architectures of ``--arch``: the MLP and the encoder presets of ``quadswarm_mj.policies``.
ARCH_NAMES = ("mlp", *ARCH_PRESETS)


@dataclass(frozen=True)
class PPOConfig:
    """PPO hyper-parameters. Sizes count agents (quads), not worlds, where noted."""

    num_worlds: int = 1024  # worlds stepped together (split evenly over the scenarios)
    unroll_length: int = 32  # control steps per agent per iteration
    num_minibatches: int = 32
    num_epochs: int = 4
    learning_rate: float = 3e-4
    entropy_cost: float = 1e-3
    discounting: float = 0.99
    gae_lambda: float = 0.95
    clipping_epsilon: float = 0.2
    reward_scaling: float = 1.0
    max_grad_norm: float = 1.0
    policy_hidden: tuple[int, ...] = (64, 64)
    value_hidden: tuple[int, ...] = (64, 64)
    activation: str = "tanh"
    normalize_observations: bool = True
    lr_schedule: str = "linear"  # "constant", or "linear": decays to lr_final_fraction at the end of the budget
    lr_final_fraction: float = 0.1
    #: agent-steps over which the linear schedule decays, counted from the run's first step (a resumed run
    #: included); None: over the run's budget (its steps, else its minutes). A run stopped before this ends at a
    #: higher rate, as a wall-clock run stopped at a checkpoint does
    lr_decay_steps: int | None = None
    init_std: float = 0.6  # initial std of the pre-tanh Gaussian (Brax's default is softplus(0) = 0.69)
    #: warm starts (--init-from): the action std set to this in every state (the std outputs' input weights
    #: zeroed); None keeps the file's state-dependent std
    warm_start_std: float | None = None
    #: floor of the pre-tanh std (Brax's ``min_std``): std = softplus(output) + this, so the policy cannot
    #: stop exploring below it (Brax's default 0.001). A warm start without ``warm_start_std`` keeps the file's
    #: std outputs, so its std rises by (this - 0.001): pair a floor with ``warm_start_std``
    min_action_std: float = 0.001
    #: temporally correlated exploration (JAX engine): each agent's standard normal action noise follows
    #: eps_t = rho eps_{t-1} + sqrt(1 - rho^2) n_t (still N(0, 1) per step; 0: independent, Brax's sampling),
    #: so a deviation lasts ~1 / (1 - rho) control steps and its effect on later rewards reaches its advantage
    noise_correlation: float = 0.0
    desync_episodes: bool = True  # truncate each world's first episode after a random number of steps
    arch: str = "mlp"  # policy network: "mlp" (policy_hidden) or a quadswarm_mj.policies.ARCH_PRESETS name
    arch_width: int | None = None  # encoders: every hidden width of the preset set to this (heads: 2x); None: as is
    #: warm starts of an MLP: 0 trains every parameter; N > 0 trains only the policy's first-layer weights of the
    #: observation components >= N (the inputs the warm start lacks, e.g. the column features) and the critic,
    #: and freezes the observation statistics, so the warm start's flight is kept exactly where those inputs are 0
    train_inputs_from: int = 0

    def __post_init__(self) -> None:
        for n in ("num_worlds", "unroll_length", "num_minibatches", "num_epochs"):
            v = getattr(self, n)
            if not isinstance(v, int) or isinstance(v, bool) or v < 1:
                raise ValueError(f"ppo.{n} must be an int >= 1, got {v!r}")
        for n in ("learning_rate", "discounting", "gae_lambda", "clipping_epsilon", "reward_scaling", "max_grad_norm",
                  "init_std"):
            v = getattr(self, n)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ValueError(f"ppo.{n} must be a finite number > 0, got {v!r}")
        ws = self.warm_start_std
        if ws is not None and not (isinstance(ws, (int, float)) and not isinstance(ws, bool) and math.isfinite(ws)
                                   and 0.001 < ws <= 10):
            raise ValueError(f"ppo.warm_start_std must be None or a number in (0.001, 10], got {ws!r}")
        ms = self.min_action_std
        if not (isinstance(ms, (int, float)) and not isinstance(ms, bool) and 0.0001 <= ms <= 1):
            raise ValueError(f"ppo.min_action_std must be a number in [0.0001, 1], got {ms!r}")
        for n in ("init_std", "warm_start_std"):
            v = getattr(self, n)
            if v is not None and v <= ms:
                raise ValueError(f"ppo.{n} must be above ppo.min_action_std ({ms}), got {v!r}")
        nc = self.noise_correlation
        if not (isinstance(nc, (int, float)) and not isinstance(nc, bool) and 0 <= nc < 1):
            raise ValueError(f"ppo.noise_correlation must be a number in [0, 1), got {nc!r}")
        if not (0 <= self.entropy_cost < 1):
            raise ValueError(f"ppo.entropy_cost must be in [0, 1), got {self.entropy_cost!r}")
        if self.discounting > 1 or self.gae_lambda > 1:
            raise ValueError("ppo.discounting and ppo.gae_lambda must be <= 1")
        if self.lr_schedule not in ("constant", "linear"):
            raise ValueError(f"ppo.lr_schedule must be 'constant' or 'linear', got {self.lr_schedule!r}")
        d = self.lr_decay_steps
        if d is not None and (not isinstance(d, int) or isinstance(d, bool) or d < 1):
            raise ValueError(f"ppo.lr_decay_steps must be None or an int >= 1 (agent-steps), got {d!r}")
        if not (0 <= self.lr_final_fraction <= 1):
            raise ValueError(f"ppo.lr_final_fraction must be in [0, 1], got {self.lr_final_fraction!r}")
        if self.activation not in ACTIVATIONS:
            raise ValueError(f"ppo.activation must be one of {tuple(ACTIVATIONS)}, got {self.activation!r}")
        if self.arch not in ARCH_NAMES:
            raise ValueError(f"ppo.arch must be one of {ARCH_NAMES}, got {self.arch!r}")
        if self.arch_width is not None and (not isinstance(self.arch_width, int) or isinstance(self.arch_width, bool)
                                            or self.arch_width < 1):
            raise ValueError(f"ppo.arch_width must be None or an int >= 1, got {self.arch_width!r}")
        t = self.train_inputs_from
        if not isinstance(t, int) or isinstance(t, bool) or t < 0:
            raise ValueError(f"ppo.train_inputs_from must be an int >= 0, got {t!r}")
        if t and self.arch != "mlp":
            raise ValueError(f"ppo.train_inputs_from needs arch 'mlp' (first-layer input rows), got {self.arch!r}")
        for n in ("policy_hidden", "value_hidden"):
            v = tuple(getattr(self, n))
            if not v or any(not isinstance(h, int) or h < 1 for h in v):
                raise ValueError(f"ppo.{n} must be a non-empty tuple of positive ints, got {v!r}")
            object.__setattr__(self, n, v)


def ppo_meta(ppo: PPOConfig) -> dict[str, Any]:
    """The configuration as JSON-ready values (tuples as lists), as policy files record it."""
    return {k: (list(v) if isinstance(v, tuple) else v) for k, v in dataclasses.asdict(ppo).items()}


def run_lr_scale(ppo: PPOConfig, env_steps: int, budget_frac: float, start: float) -> float:
    """Learning-rate factor of a run at ``env_steps`` agent-steps (from its first step) and ``budget_frac``
    of its budget: over ``ppo.lr_decay_steps`` when set, else over the budget from ``start``."""
    if ppo.lr_decay_steps is not None:
        return linear_lr_scale(ppo, env_steps / ppo.lr_decay_steps)
    return linear_lr_scale(ppo, budget_frac, start)


def linear_lr_scale(ppo: PPOConfig, frac: float, start: float = 1.0) -> float:
    """Learning-rate factor at budget fraction ``frac``: constant ``start``, or linear from ``start`` to
    ``lr_final_fraction`` (resumed runs start from the checkpoint's factor)."""
    if ppo.lr_schedule != "linear":
        return start
    end = min(ppo.lr_final_fraction, start)
    return start - (start - end) * min(max(frac, 0.0), 1.0)
