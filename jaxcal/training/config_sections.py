"""The sections of a training run's configuration: data, environment, budget,
simulated units and output (:class:`jaxcal.training.config.TrainConfig` holds one of
each; ``jaxcal.training.config`` re-exports them). Frozen dataclasses that check their
own fields.
"""

from __future__ import annotations

import dataclasses
import math
import typing
from typing import Literal

from jaxcal.envs.tracking import check_action_options


def check_choices(cfg: object, prefix: str) -> None:
    """Raises ValueError naming ``prefix + field`` for a ``Literal`` field set to a
    value outside its choices."""
    hints = typing.get_type_hints(type(cfg))
    for field in dataclasses.fields(cfg):
        if typing.get_origin(hints[field.name]) is not Literal:
            continue
        choices = typing.get_args(hints[field.name])
        value = getattr(cfg, field.name)
        if value not in choices:
            quoted = [repr(c) for c in choices]
            raise ValueError(
                f"{prefix}{field.name} must be {', '.join(quoted[:-1])} or "
                f"{quoted[-1]}, got {value!r}"
            )


@dataclasses.dataclass(frozen=True)
class DataConfig:
    """Which data file a run trains on, and how it is read.

    An ``.h5`` file in the N-CMAPSS layout has dev / test splits; any other file
    (``.csv``, ``.parquet``, NASA C-MAPSS ``.txt``) is read as rows of the model's
    variables (:func:`jaxcal.data.readers.read_dataset`): a ``split`` column
    (train / val / test, or dev / test) is used when present, else whole units are
    held out (``test_units``, ``val_units``).
    """

    name: str = "cmapss"  # preset name (run names use it; "": the file's stem)
    path: str = "data/cmapss.h5"  # the data file
    # jaxcal.generate preset that builds `path` when the file is missing ("": never)
    generate: str = "cmapss"
    stride: int = 1  # keep every stride-th row (NASA files are 1 Hz)
    # held-out dev units for progress and tuning; None: the last val_fraction of the
    # dev units; (): none. Test units are the file's test split, scored at the end.
    val_units: tuple[int, ...] | None = None
    val_fraction: float = 0.15
    # units held out for the final test of a file without a split column; None: the
    # last test_fraction of its units (N-CMAPSS files: their test split, always)
    test_units: tuple[int, ...] | None = None
    test_fraction: float = 0.2
    # rows with NaN / Inf in w, the sensors or theta: "error" refuses the file (the
    # message names file, columns, first rows, counts); "drop" drops and logs them
    nonfinite: Literal["error", "drop"] = "error"
    # what a file's true-parameter columns are for: "use" (also the action box,
    # their range widened by env.theta_margin, and the fixed parameters' values) or
    # "score" (test scores only: the box is the model's bounds)
    labels: Literal["use", "score"] = "use"
    # file column names the reader maps to jaxcal names, "<file name>:<jaxcal name>"
    # (e.g. T_24:T24); any other unknown or missing column name is an error
    rename: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        if self.stride < 1:
            raise ValueError(f"dataset.stride must be >= 1, got {self.stride}")
        check_choices(self, "dataset.")
        bad = [p for p in self.rename if len(p.split(":")) != 2 or "" in p.split(":")]
        if bad:
            raise ValueError(
                f"dataset.rename must be <file name>:<jaxcal name> pairs (e.g. "
                f"dataset.rename=T_24:T24,T_30:T30), got {list(bad)}"
            )
        if not 0.0 < self.test_fraction < 1.0:
            raise ValueError(
                f"dataset.test_fraction must be in (0, 1), got {self.test_fraction}"
            )
        if not 0.0 <= self.val_fraction < 1.0:
            raise ValueError(
                f"dataset.val_fraction must be in [0, 1), got {self.val_fraction}"
            )


@dataclasses.dataclass(frozen=True)
class TrackingConfig:
    """Run-level settings of the tracking environment (``EnvConfig`` adds the data's
    dimensions)."""

    episode_length: int = 200  # steps per training window
    # the action box is the dev range of theta widened by this share on each side
    theta_margin: float = 0.1
    # "absolute": the action sets theta (the paper's); "increment": it changes theta,
    # gated by the residual (jaxcal.envs.increment: a learned feedback that drives
    # the tracking error to zero instead of guessing theta)
    action: Literal["absolute", "increment"] = "absolute"
    # incremental actions: the largest change per step, as a share of the box width
    max_increment: float = 0.5
    # "squared": the paper's tracking cost; "log": log(1 + cost / cost_floor^2), the
    # same weight for halving the error at every scale (jaxcal.envs.tracking.EnvConfig)
    cost: Literal["squared", "log"] = "squared"
    cost_floor: float = 1e-4
    # where a deployed incremental policy starts theta: "centre" of the box, or the
    # model's nominal values ("prior", what the UKF starts from)
    start: Literal["centre", "prior"] = "centre"
    # incremental actions: the observation also holds the residual's Gauss-Newton
    # step through the model's Jacobian and the stream's age
    # (jaxcal.envs.increment.gauss_newton_features): "on", "off", or "auto" (on when
    # the outputs are at least as many as the calibrated parameters, so that one
    # sample's step determines theta), or "filter": as "auto", and where that is on,
    # the step of an extended Kalman filter on theta carried along the stream
    # (jaxcal.envs.increment.filter_feature), a share filter_gain of which is the
    # untrained policy's action
    gauss_newton: Literal["off", "on", "auto", "filter"] = "off"
    # with gauss_newton=filter: the untrained policy takes this share of the
    # filter's step and learns a correction of it (0: it learns the whole action).
    # 1: the untrained policy follows the extended Kalman filter, its noise the
    # simulated units' (given or estimated; results/policy_any_model)
    filter_gain: float = 1.0
    # with gauss_newton=filter: the filter's random walk per sample, in half-widths
    # of the box (the UKF's q, 0.01 by default): give the UKF's own where it is
    # tuned (the battery example: 5e-4, its 17,000-sample cells drift slowly)
    filter_q: float = 0.01
    # with gauss_newton=filter: the filter's prior std, in half-widths of the box
    # (the UKF's prior_std, 1 by default; the battery example's UKF: 0.25)
    filter_prior_std: float = 1.0
    # with gauss_newton=filter: a unit gain is the extended Kalman filter: the
    # feature is its whole step at any residual (the increment's gate divided out)
    # and on a model with memory it filters the state with theta
    # (jaxcal.envs.joint_filter). False: the gate's small-residual slope only, the
    # state as simulated
    filter_whole: bool = False
    # weight of the theta error in the cost where the true theta is known (the
    # simulated training units; jaxcal.envs.tracking.theta_error_cost): the policy
    # is rewarded for the parameters themselves, not only for tracking through
    # them. 0: tracking alone (the paper's)
    theta_cost: float = 0.0
    # with gauss_newton=filter on a static model: the filter weighs each output by
    # the noise its innovations show beyond what theta explains, averaged over this
    # many samples (jaxcal.envs.increment.adapted_noise_scale): a biased, drifting
    # or mis-scaled sensor is weighed less. 0: the declared noise throughout
    filter_adapt: int = 0

    def __post_init__(self) -> None:
        if not (isinstance(self.filter_adapt, int) and self.filter_adapt >= 0):
            raise ValueError(
                f"env.filter_adapt must be an int >= 0 (samples), got "
                f"{self.filter_adapt!r}"
            )
        if not (math.isfinite(self.theta_cost) and self.theta_cost >= 0):
            raise ValueError(f"env.theta_cost must be >= 0, got {self.theta_cost!r}")
        check_action_options(
            self.action, self.max_increment, self.cost, self.cost_floor
        )
        if self.episode_length < 1:
            raise ValueError(
                f"env.episode_length must be >= 1, got {self.episode_length}"
            )
        check_choices(self, "env.")
        if self.gauss_newton in ("on", "filter") and self.action != "increment":
            raise ValueError(
                f"env.gauss_newton={self.gauss_newton} needs env.action=increment "
                "(it observes an incremental action's residual)"
            )
        if not self.filter_q > 0.0 or not self.filter_prior_std > 0.0:
            raise ValueError(
                "env.filter_q and env.filter_prior_std must be > 0, got "
                f"{self.filter_q}, {self.filter_prior_std}"
            )
        if not 0.0 <= self.filter_gain <= 1.0:
            raise ValueError(
                f"env.filter_gain must be in [0, 1], got {self.filter_gain}"
            )
        if self.theta_margin < 0:
            raise ValueError(f"env.theta_margin must be >= 0, got {self.theta_margin}")


@dataclasses.dataclass(frozen=True)
class BudgetConfig:
    """How long the policy trains, how often the host scores and saves, and which
    policy the run keeps.

    Changing these fields does not change the training trajectory, so a run may be
    resumed (or extended) with a different budget.
    """

    num_chunks: int = 150  # jitted chunks of runner.num_steps_per_chunk iterations
    eval_every: int = 5  # chunks between validation scores (0: never)
    ckpt_every: int = 5  # chunks between checkpoints (the last chunk is always saved)
    # Wall-clock limit of the whole job in seconds, from its start (data generation
    # included): training stops after the chunk that crosses it, the final scoring
    # still runs. None: no limit. A safety net for a loaded machine; a run stopped by
    # it depends on the machine's speed (final.json says so).
    time_limit_s: float | None = 1080.0
    # The policy the run keeps (scored on test, loaded by jaxcal.deploy): "last", or
    # "val_tracking": the one with the lowest validation *tracking* RMSE among the
    # scored chunks (label-free early stopping: theta labels are never used).
    # "sim_theta": the lowest theta RMSE (in box widths) on units simulated along the
    # validation units' conditions (jaxcal.training.data.simulated; no label either).
    select: Literal["last", "val_tracking", "sim_theta"] = "val_tracking"
    # Early stopping: the session ends after this many scored chunks in a row that
    # do not lower the selection's score (scored every eval_every chunks; None:
    # never). A training that cannot improve on its best, often the untrained
    # start of an actor with a prior, then stops instead of spending its budget.
    patience: int | None = None
    # The actor that is deployed: "target", the Polyak-averaged policy of Algorithm 1
    # (theta-bar <- tau theta + (1 - tau) theta-bar; LAC and CLAC keep one, SAC has
    # none and falls back to its online actor), or "online", the last gradient iterate.
    policy: Literal["target", "online"] = "target"
    # Time to target: final.json reports the job's wall time at the first scoring
    # whose validation theta RMSE <= this value (the labelled validation units,
    # scored anyway; reporting only: selection reads the tracking). None: off. The
    # dataset presets' values are in TARGET_THETA_RMSE (cmapss: 2.5e-4).
    target_theta_rmse: float | None = None
    # An actor without a prior starts as a random network, never a candidate: its
    # untrained start is scored on the validation units after the training for
    # final.json's training_gain only with this set (one more validation pass).
    score_random_start: bool = False

    def __post_init__(self) -> None:
        if self.target_theta_rmse is not None and not self.target_theta_rmse > 0:
            raise ValueError(
                "budget.target_theta_rmse must be > 0 or None, got "
                f"{self.target_theta_rmse!r}"
            )
        if self.patience is not None and not (
            isinstance(self.patience, int) and self.patience >= 1
        ):
            raise ValueError(
                "budget.patience must be an integer >= 1 or None, got "
                f"{self.patience!r}"
            )
        if self.num_chunks < 0 or self.eval_every < 0 or self.ckpt_every < 1:
            raise ValueError(
                "budget.num_chunks and budget.eval_every must be >= 0 and "
                f"budget.ckpt_every >= 1, got {self}"
            )
        check_choices(self, "budget.")


@dataclasses.dataclass(frozen=True)
class SimulationConfig:
    """Units simulated from the model wherever a run needs true theta
    (:mod:`jaxcal.training.data.simulated`): the user's labels are for scoring only."""

    # what the policy trains on: "data" (the training units, cost on their noisy
    # outputs), "simulated" (simulated copies of them, cost on the noise-free
    # outputs) or "both"
    train: Literal["data", "simulated", "both"] = "data"
    copies: int = 1  # simulated copies of each training unit
    # share of simulated units whose parameters stay constant
    constant_share: float = 0.25
    # the units the uncertainty band is fitted on: "simulated" (along the validation
    # units' conditions), "labelled" (the validation units' own labels) or "auto"
    # (labelled when the validation units carry labels, else simulated)
    band: Literal["auto", "simulated", "labelled"] = "auto"
    band_copies: int = 8  # simulated copies of each validation unit for the band
    # the theta paths of the units the band is fitted and the policy selected on:
    # "box" (drawn across the box, jaxcal.training.data.sim_paths.theta_paths) or "data"
    # (the UKF's estimates on the training and validation units, smoothed:
    # jaxcal.training.data.sim_paths.estimated_drifts)
    paths: Literal["box", "data"] = "box"
    # the log cost's floor when training on simulated units: "noise" (the noise
    # std's RMS in the cost's normalised units) or "env" (env.cost_floor as given)
    cost_floor: Literal["noise", "env"] = "env"
    # share of the simulated training units that carry one undeclared effect on
    # their outputs (a sensor bias, step, drift, gain error or AR(1)-coloured
    # noise, 1-4 noise stds: jaxcal.training.data.sim_effects), their cost still on the
    # noise-free outputs: the policy learns to hold under model error. 0: none
    effects: float = 0.0

    def __post_init__(self) -> None:
        if not 0.0 <= self.effects <= 1.0:
            raise ValueError(f"simulate.effects must be in [0, 1], got {self.effects}")
        check_choices(self, "simulate.")
        if self.copies < 1 or self.band_copies < 1:
            raise ValueError(
                "simulate.copies and simulate.band_copies must be >= 1, got "
                f"{self.copies}, {self.band_copies}"
            )
        if not 0.0 <= self.constant_share <= 1.0:
            raise ValueError(
                f"simulate.constant_share must be in [0, 1], got {self.constant_share}"
            )


@dataclasses.dataclass(frozen=True)
class TuneConfig:
    """The kept actor tuned by gradient through the deployed filter on simulated
    units' theta error, kept where the selection units agree
    (:mod:`jaxcal.training.stages.tune`). It does not change the actor-critic's
    training, so a run may be resumed with other values."""

    steps: int = 0  # Adam steps (0: off)
    lr: float = 3e-4  # Adam's step size
    batch_units: int = 16  # simulated training units per step
    # rows of a unit per step: longer units are cut to a window at a random row
    # (the filter starts afresh there), so a step's cost does not grow with them
    window: int = 2048
    eval_every: int = 25  # steps between scorings on the selection units
    patience: int = 3  # scorings in a row without a better policy: stop
    clip: float = 1.0  # global gradient-norm clip (a long recursion's gradient)
    # a tuned policy is kept only if its theta RMSE on each guard set (clean,
    # drawn across the box, with effects: Simulations.guard_units) is at most
    # (1 + this) x the start's
    clean_tolerance: float = 0.15
    # a share of the tuning units with an undeclared effect (sim_effects.KINDS).
    # With it the score a tuned policy must lower is the mean over the clean
    # selection units and the effects guard, each over the start's, and the clean
    # selection units may not lose at all (clean_limit): tuned on effects alone,
    # a policy holds a bias better but loses on clean units
    effects: float = 0.0
    clean_limit: float = 1.0  # with effects: clean selection error <= this x start
    # with effects: the effects guard's weight in the score (the clean selection
    # units' the rest); 1: the effects alone, the clean units a limit only
    effects_weight: float = 0.5
    # tune the random walk of output-bias states in the filter beside the actor
    # (jaxcal.envs.bias_states): a sensor's slow error estimated, not read as theta
    bias: bool = False
    bias_lr: float = 0.05  # Adam's step on the biases' log walk (natural log)

    def __post_init__(self) -> None:
        if not self.bias_lr > 0:
            raise ValueError(f"tune.bias_lr must be > 0, got {self.bias_lr!r}")
        if not (
            0.0 <= self.effects <= 1.0
            and self.clean_limit > 0
            and 0.0 <= self.effects_weight <= 1.0
        ):
            raise ValueError(
                "tune.effects and tune.effects_weight must be in [0, 1] and "
                f"tune.clean_limit > 0, got {self}"
            )
        if self.steps < 0 or min(self.batch_units, self.eval_every, self.window) < 1:
            raise ValueError(
                "tune.steps must be >= 0, tune.batch_units, tune.eval_every and "
                f"tune.window >= 1, got {self}"
            )
        if not (self.lr > 0 and self.clip > 0 and self.patience >= 1) or not (
            self.clean_tolerance >= 0
        ):
            raise ValueError(
                f"tune.lr and tune.clip must be > 0, tune.patience >= 1, got {self}"
            )


@dataclasses.dataclass(frozen=True)
class OutputConfig:
    """Where and what a run writes."""

    runs_dir: str = "runs"  # parent folder of run folders
    # run folder name, one folder inside runs_dir (no '/', '\\', '..', leading '.');
    # "": <dataset>-<agent>-<dynamics>-s<seed>[-preset]
    name: str = ""
    # save the replay buffer in checkpoints: exact resumes, but the checkpoint grows by
    # buffer_size x (2 O + A + 2) x 4 bytes; without it a resume refills the buffer
    save_buffer: bool = True
    max_to_keep: int = 2  # checkpoints kept
    progress: bool = True  # tqdm bars
