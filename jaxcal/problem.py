"""The one calibration problem: model + declared parameters + used outputs + data +
normalisation.

Every consumer reads the same object: the calibrators (:func:`jaxcal.calibrate`), the
tracking environment and the training job, deployment and evaluation. It answers the
questions each of them used to answer on its own:

* which parameters are calibrated (``theta_names``, ``P``) and where the others are
  held (``theta_base``, all ``P_all`` values);
* the box the calibrated parameters live in (``theta_low``/``theta_high``: the
  model's bounds, or the data's labelled range widened by a margin);
* which outputs are used (``output_names``, ``S``) and their normalisation, and the
  conditions' (:class:`~jaxcal.data.normalisation.Normalisation`, over the training
  rows);
* the measurement noise per output (``noise_std``), given or estimated;
* the range of the training data (``input_range``): a later sample far outside it is
  flagged instead of being silently used.

It is a frozen, identity-hashed container of host numpy arrays; its
:meth:`Problem.to_json` / :meth:`Problem.from_json` pair is what a run folder stores.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np

from jaxcal.data.dataset import Dataset
from jaxcal.data.normalisation import Normalisation
from jaxcal.model import Model

# Half-width of the box of a declared parameter that is constant in labelled data.
CONSTANT_THETA_HALF_WIDTH = 0.01
# A labelled parameter "varies" when its range exceeds this (files store exact zeros).
VARYING_TOLERANCE = 1e-9
# The one default of a missing noise std, before anything is estimated: this share of
# each output's spread (the paper's r = 0.01 in units of the training std). The front
# door then estimates the noise from the data; what cannot (a streamed fleet, a run
# that stored none) keeps this start and says so in ``noise_source``.
PROVISIONAL_NOISE_SHARE = 0.01


def labelled_box(
    theta: np.ndarray, theta_margin: float
) -> tuple[np.ndarray, np.ndarray]:
    """The box of labelled rows ``theta [N, P]``: their range widened by
    ``theta_margin`` of its width on each side (a constant parameter by
    :data:`CONSTANT_THETA_HALF_WIDTH`) — the paper's action box."""
    low, high = theta.min(axis=0), theta.max(axis=0)
    width = high - low
    margin = np.where(
        width > VARYING_TOLERANCE, theta_margin * width, CONSTANT_THETA_HALF_WIDTH
    )
    return low - margin, high + margin


class Transition(NamedTuple):
    """A model with memory on the calibrated parameters (:meth:`Problem.transition`).

    ``init(w0 [W], theta [P]) -> z [Z]``; ``step(z, w [W], theta [P]) -> (z', x [S])``;
    ``num_states`` is ``Z`` (0 for a static model).
    """

    init: Callable
    step: Callable
    num_states: int


class InputRange(NamedTuple):
    """The training data's box ``[low, high]`` of ``w`` and ``x``."""

    w_low: np.ndarray
    w_high: np.ndarray
    x_low: np.ndarray
    x_high: np.ndarray


@dataclasses.dataclass(frozen=True, eq=False)
class Problem:
    """A calibration problem (see the module docstring).

    Attributes:
        model: the physics model.
        theta_names: ``P`` calibrated parameter names.
        output_names: ``S`` used output names.
        theta_base: ``[P_all]`` values of every model parameter (undeclared held here).
        theta_low, theta_high: ``[P]`` box of the calibrated parameters.
        norm: training :class:`Normalisation` (float64 arrays; a training run's is
            computed in the run's dtype and carried unchanged:
            :func:`jaxcal.training.data.calibration.training_norm`).
        noise_std: ``[S]`` measurement noise std per used output.
        input_range: training :class:`InputRange` (flags far-out samples).
        noise_source: ``"given"`` or how it was estimated.
    """

    model: Model
    theta_names: tuple[str, ...]
    output_names: tuple[str, ...]
    theta_base: np.ndarray
    theta_low: np.ndarray
    theta_high: np.ndarray
    norm: Normalisation
    noise_std: np.ndarray
    input_range: InputRange | None = None
    noise_source: str = "given"

    @classmethod
    def build(
        cls,
        model: Model,
        data: Dataset,
        *,
        theta: Sequence[str] | None = None,
        outputs: Sequence[str] | None = None,
        noise: Mapping[str, float] | Sequence[float] | None = None,
        box: str = "bounds",
        margin: float = 0.1,
    ) -> Problem:
        """The problem of ``model`` on (training) ``data``.

        Args:
            model: the model.
            data: its rows (columns checked against the model).
            theta: calibrated parameter names (default: all the model's).
            outputs: used outputs (default: every model output the data has).
            noise: output name -> noise std (or ``[S]``); ``None``: estimated
                later by the calibrator front (:func:`jaxcal.calibrate`), until
                then 1 % of each output's spread.
            box: ``"bounds"``: the model's parameter bounds; ``"data"``: the range
                of the data's true parameters widened by ``margin`` of its width
                (the paper's action box; needs labelled data).
            margin: see ``box``.
        """
        data = data.for_model(model, outputs)
        theta = tuple(theta) if theta else model.parameter_names
        idx = model.parameter_index(theta)
        low, high = (b[idx] for b in model.bounds)
        base = model.nominal.copy()
        if box == "data":
            if data.theta is None or not set(theta) <= set(data.theta_names):
                raise ValueError(
                    "box='data' needs the true values of every calibrated parameter "
                    f"{list(theta)} in the data (found {list(data.theta_names)})"
                )
            cols = [data.theta_names.index(n) for n in theta]
            low, high = labelled_box(data.theta[:, cols], margin)
            for j, name in enumerate(data.theta_names):
                base[model.parameter_names.index(name)] = data.theta[:, j].mean()
        elif box != "bounds":
            raise ValueError(f"box must be 'bounds' or 'data', got {box!r}")
        seen = ~np.isnan(data.x).all(axis=0)  # a partial row misses some outputs
        if not seen.all():
            unseen = [n for n, s in zip(data.output_names, seen, strict=True) if not s]
            raise ValueError(
                f"{data.source}: output column(s) {unseen} hold no value (every row "
                "missing); leave them out with outputs=[...]"
            )
        norm = Normalisation.of(data.w, data.x)
        noise_std, source = _noise_vector(noise, data.output_names, norm)
        return cls(
            model=model,
            theta_names=theta,
            output_names=data.output_names,
            theta_base=base,
            theta_low=np.asarray(low, np.float64),
            theta_high=np.asarray(high, np.float64),
            norm=norm,
            noise_std=noise_std,
            input_range=InputRange(  # missing outputs (NaN) left out
                data.w.min(0),
                data.w.max(0),
                np.nanmin(data.x, 0),
                np.nanmax(data.x, 0),
            ),
            noise_source=source,
        )

    # ---------------------------------------------------------------- derived

    @property
    def theta_index(self) -> list[int]:
        """Positions of the calibrated parameters among the model's."""
        return self.model.parameter_index(self.theta_names)

    @property
    def theta_prior(self) -> np.ndarray:
        """``[P]`` prior mean: the base (nominal) values of the calibrated parameters,
        clipped into the box."""
        prior = self.theta_base[self.theta_index]
        return np.clip(prior, self.theta_low, self.theta_high)

    @property
    def theta_centre(self) -> np.ndarray:
        """``[P]`` centre of the box (the paper's prior mean for the UKF and LS)."""
        return 0.5 * (self.theta_low + self.theta_high)

    @property
    def theta_half_width(self) -> np.ndarray:
        """``[P]`` half-width of the box (the parameters' natural scale)."""
        return 0.5 * (self.theta_high - self.theta_low)

    def measure(self):
        """``F(w [W], theta [P]) -> x [S]`` on the calibrated parameters and used
        outputs (the undeclared parameters held at ``theta_base``)."""
        return self.model.restrict(self.theta_names, self.output_names, self.theta_base)

    def transition(self) -> Transition:
        """The restricted model with its memory: ``init(w0, theta [P]) -> z [Z]`` and
        ``step(z, w, theta [P]) -> (z', x [S])`` on the calibrated parameters and
        used outputs. A static model is the stateful one with ``Z = 0`` (``z`` an
        empty array, ``step`` is ``F``), so every calibrator takes both through this
        one path."""
        model = self.model
        declared = np.asarray(self.theta_index)
        used = np.asarray(model.output_index(self.output_names))
        base = np.asarray(self.theta_base)

        def full(theta):
            return jnp.asarray(base, theta.dtype).at[declared].set(theta)

        def init(w0, theta):
            z0 = model.init_state(w0, full(theta))
            return jnp.asarray(z0, theta.dtype).reshape(len(model.states))

        def step(z, w, theta):
            z_next, x, _ = model.step(z, w, full(theta))
            return jnp.asarray(z_next, z.dtype).reshape(z.shape), x[used]

        return Transition(init=init, step=step, num_states=len(model.states))

    def with_noise(self, noise_std: np.ndarray, source: str) -> Problem:
        """The same problem with another noise vector ``[S]``."""
        noise_std = np.asarray(noise_std, np.float64)
        if noise_std.shape != (len(self.output_names),) or not np.all(noise_std > 0):
            raise ValueError(
                f"noise std must be [{len(self.output_names)}] and > 0, got {noise_std}"
            )
        return dataclasses.replace(self, noise_std=noise_std, noise_source=source)

    # ---------------------------------------------------------------- storage

    def to_json(self) -> dict:
        """Everything but the model object (stored by name in run folders)."""
        return {
            "model": self.model.name,
            "theta_names": list(self.theta_names),
            "output_names": list(self.output_names),
            "theta_base": self.theta_base.tolist(),
            "theta_low": self.theta_low.tolist(),
            "theta_high": self.theta_high.tolist(),
            "norm": {k: np.asarray(v).tolist() for k, v in self.norm._asdict().items()},
            "noise_std": self.noise_std.tolist(),
            "noise_source": self.noise_source,
            "input_range": None
            if self.input_range is None
            else {
                k: np.asarray(v).tolist() for k, v in self.input_range._asdict().items()
            },
        }

    @classmethod
    def from_json(cls, data: Mapping, model: Model) -> Problem:
        """Inverse of :meth:`to_json` for ``model``."""
        arr = lambda v: np.asarray(v, np.float64)  # noqa: E731
        rng = data.get("input_range")
        return cls(
            model=model,
            theta_names=tuple(data["theta_names"]),
            output_names=tuple(data["output_names"]),
            theta_base=arr(data["theta_base"]),
            theta_low=arr(data["theta_low"]),
            theta_high=arr(data["theta_high"]),
            norm=Normalisation(**{k: arr(v) for k, v in data["norm"].items()}),
            noise_std=arr(data["noise_std"]),
            input_range=None
            if rng is None
            else InputRange(**{k: arr(v) for k, v in rng.items()}),
            noise_source=str(data.get("noise_source", "given")),
        )


def _noise_vector(noise, names: Sequence[str], norm: Normalisation):
    """The ``[S]`` noise std of a mapping / sequence / None (1 % of the spread)."""
    if noise is None:
        return provisional_noise(norm.x_std)
    if isinstance(noise, Mapping):
        unknown = [k for k in noise if k not in names]
        missing = [n for n in names if n not in noise]
        if unknown or missing:
            raise ValueError(
                f"noise: give a std for every used output {list(names)}"
                + (f"; unknown {unknown}" if unknown else "")
                + (f"; missing {missing}" if missing else "")
            )
        values = np.array([float(noise[n]) for n in names])
    else:
        values = np.asarray(noise, np.float64).reshape(-1)
        if values.shape != (len(names),):
            raise ValueError(
                f"noise must have {len(names)} entries, got {values.shape}"
            )
    if not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(f"noise std must be finite and > 0, got {values.tolist()}")
    return values, "given"


def provisional_noise(spread):
    """``(noise_std [S], noise_source)``: the default of a missing noise,
    :data:`PROVISIONAL_NOISE_SHARE` of each output's ``spread`` (float64)."""
    share = PROVISIONAL_NOISE_SHARE * np.asarray(spread, np.float64)
    return (
        share,
        f"provisional ({PROVISIONAL_NOISE_SHARE * 100:g} % of each output's spread)",
    )
