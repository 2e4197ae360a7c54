"""Static hyperparameters of the SAC, LAC and CLAC agents.

Defaults are the paper's appendix table (Tian et al., "Real-Time Model Calibration with
Deep Reinforcement Learning", table "LAC and CLAC Hyperparameters"): actor lr 1e-4,
critic lr 3e-4, gamma 0.99, tau 0.005, alpha_3 = 1, target entropy -d, initial
temperature 2, initial Lyapunov multiplier 0.1, 2 x 256 leaky-ReLU networks. Values the
paper leaves open are taken from the authors' reference implementation and say so.

Naming: the paper calls the entropy temperature beta and the smoothness multiplier
alpha; the reference code calls the entropy temperature ``alpha`` and the smoothness
multiplier ``beta``; both call the Lyapunov multiplier lambda (``labda``). We name them
by role: ``entropy_temperature``, ``lyapunov_multiplier``, ``smoothness_multiplier``.

The minibatch size (256 in the paper) is a property of the training loop and lives in
:class:`jaxcal.training.runner.RunnerConfig`.
"""

from __future__ import annotations

import dataclasses


def _check_positive(cfg: object, *names: str) -> None:
    for name in names:
        value = getattr(cfg, name)
        if not value > 0:
            raise ValueError(f"{type(cfg).__name__}.{name} must be > 0, got {value!r}")


@dataclasses.dataclass(frozen=True)
class _ActorCriticConfig:
    """Fields shared by every agent (subclasses add the algorithm-specific ones)."""

    # Hidden layer widths of the policy network (paper: two layers of 256).
    actor_hidden_sizes: tuple[int, ...] = (256, 256)
    # Hidden layer widths of the critic (Q or Lyapunov) network (paper: 2 x 256).
    critic_hidden_sizes: tuple[int, ...] = (256, 256)
    # Negative slope of the leaky ReLU; 0.2 is the TensorFlow default that the
    # reference implementation used (flax's own default is 0.01).
    leaky_relu_slope: float = 0.2
    # Clip of the pre-tanh log standard deviation (SAC's usual (-20, 2); the CLAC
    # reference code used (-2, 1)).
    log_std_min: float = -20.0
    log_std_max: float = 2.0
    # Adam learning rates (paper appendix).
    actor_lr: float = 1e-4
    critic_lr: float = 3e-4
    # Discount factor gamma and Polyak coefficient tau of the target networks.
    gamma: float = 0.99
    tau: float = 0.005
    # Initial entropy temperature (the paper's beta, "Initial beta = 2").
    initial_entropy_temperature: float = 2.0
    # Adam learning rate of log(entropy temperature); the reference ties it to actor_lr.
    entropy_temperature_lr: float = 1e-4
    # Target entropy H_t; None means -d with d the action dimension (paper).
    target_entropy: float | None = None
    # A prior the actor's mean is a correction of: (start, gain) adds
    # arctanh(gain * obs[start : start + A]) to the pre-tanh mean, so that the
    # untrained actor already takes that share of the observed step (the filter
    # step of env.gauss_newton=filter, set by the training from the env; residual
    # policy learning: Silver et al. 2018, arXiv:1812.06298). None: no prior.
    actor_prior: tuple[int, float] | None = None

    def __post_init__(self) -> None:
        for name in ("actor_hidden_sizes", "critic_hidden_sizes"):
            sizes = getattr(self, name)
            if not isinstance(sizes, tuple) or not sizes or min(sizes) < 1:
                raise ValueError(
                    f"{type(self).__name__}.{name} must be a non-empty tuple of "
                    f"positive ints, got {sizes!r}"
                )
        _check_positive(
            self,
            "actor_lr",
            "critic_lr",
            "initial_entropy_temperature",
            "entropy_temperature_lr",
        )
        if not 0.0 <= self.gamma < 1.0:
            raise ValueError(f"gamma must be in [0, 1), got {self.gamma!r}")
        if not 0.0 < self.tau <= 1.0:
            raise ValueError(f"tau must be in (0, 1], got {self.tau!r}")
        if not self.log_std_min < self.log_std_max:
            raise ValueError(
                f"log_std_min ({self.log_std_min}) must be < log_std_max "
                f"({self.log_std_max})"
            )

    def resolved_target_entropy(self, action_size: int) -> float:
        """Target entropy H_t: the configured value, or -d (paper appendix)."""
        if self.target_entropy is None:
            return -float(action_size)
        return float(self.target_entropy)


@dataclasses.dataclass(frozen=True)
class SACConfig(_ActorCriticConfig):
    """Soft actor-critic on costs (Haarnoja et al. 2018) with twin Q critics."""

    # Number of Q critics; the target and the actor use the maximum (pessimistic for
    # costs, the mirror image of SAC's clipped double-Q minimum over rewards).
    num_critics: int = 2

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(self, "num_critics")


@dataclasses.dataclass(frozen=True)
class LACConfig(_ActorCriticConfig):
    """Lyapunov actor-critic (Han et al. 2020; paper eq. LAC)."""

    # alpha_3: speed of the energy decrease in the Lyapunov condition (paper: 1).
    alpha3: float = 1.0
    # Initial Lyapunov multiplier lambda (paper appendix: 0.1).
    initial_lyapunov_multiplier: float = 0.1
    # Upper clip of lambda (reference code: lambda in [0, 1]).
    max_lyapunov_multiplier: float = 1.0
    # Adam learning rate of log(lambda); the reference ties it to actor_lr.
    lyapunov_multiplier_lr: float = 1e-4

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(
            self,
            "initial_lyapunov_multiplier",
            "max_lyapunov_multiplier",
            "lyapunov_multiplier_lr",
        )
        if self.alpha3 < 0:
            raise ValueError(f"alpha3 must be >= 0, got {self.alpha3!r}")
        if self.initial_lyapunov_multiplier > self.max_lyapunov_multiplier:
            raise ValueError(
                "initial_lyapunov_multiplier must be <= max_lyapunov_multiplier, got "
                f"{self.initial_lyapunov_multiplier} > {self.max_lyapunov_multiplier}"
            )


@dataclasses.dataclass(frozen=True)
class CLACConfig(LACConfig):
    """Constrained LAC (paper eq. CLAC): LAC plus an action-smoothness penalty."""

    # Initial smoothness multiplier (the paper's alpha; not given in the paper).
    initial_smoothness_multiplier: float = 0.1
    # Upper clip of the smoothness multiplier (reference code: [0, 1]).
    max_smoothness_multiplier: float = 1.0
    # Adam learning rate of log(smoothness multiplier) (reference code: 0.01).
    smoothness_multiplier_lr: float = 1e-2
    # Target of the mean deterministic action change ||pi*(s) - pi*(s_near)|| in the
    # squashed [-1, 1] action space (reference code: 0.02).
    smoothness_threshold: float = 0.02

    def __post_init__(self) -> None:
        super().__post_init__()
        _check_positive(
            self,
            "initial_smoothness_multiplier",
            "max_smoothness_multiplier",
            "smoothness_multiplier_lr",
            "smoothness_threshold",
        )
        if self.initial_smoothness_multiplier > self.max_smoothness_multiplier:
            raise ValueError(
                "initial_smoothness_multiplier must be <= max_smoothness_multiplier"
            )
