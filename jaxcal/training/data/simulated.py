"""Labelled units simulated from the model: what a run needs true theta for.

The model is known, so a run never needs the user's labels: wherever training, the
surrogate D or the uncertainty band needs true theta, units are simulated along the
user's own operating conditions. A simulated unit keeps a real unit's
conditions ``w`` and length, draws a theta trajectory inside the action box, runs the
model along it (a model with memory from its own initial state) and adds Gaussian
output noise of the problem's std. Its noise-free outputs are kept as well: the
tracking cost of a simulated unit compares the prediction with them
(:class:`~jaxcal.envs.env_data.EnvParams` ``x_target``), so the policy is rewarded
for precision below the noise level, which the cost of a noisy target cannot see
(``log(e + n)^2`` is flat in ``e`` for ``|e| << |n|``).

Theta trajectories are drawn across the box, or follow the drifts the UKF finds in
the data (``simulate.paths``): :mod:`jaxcal.training.data.sim_paths`.

The noise is the problem's: given (``noise=`` of the command line), else estimated
by the front door's screening (a UKF pass over the training units,
:func:`jaxcal.calibrators.front.door.calibrate`).
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import jax
import numpy as np

from jaxcal.calibrators.methods.e2e.simulated import simulate_fleet
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem
from jaxcal.training.data.calibration import output_spread
from jaxcal.training.data.sim_effects import add_effects
from jaxcal.training.data.sim_paths import (
    drift_paths,
    estimated_drifts,
    front_ukf,
    theta_paths,
)


def simulate_units(
    problem: Problem,
    units: Padded,
    key: jax.Array,
    *,
    copies: int = 1,
    constant_share: float = 0.25,
    drifts: np.ndarray | None = None,
    effects: float = 0.0,
) -> tuple[Padded, np.ndarray]:
    """``copies`` simulated fleets along ``units``' conditions (module doc), theta
    along the ``drifts`` where given (:func:`estimated_drifts`, in turn over the
    copies' units: :func:`drift_paths`), else drawn (:func:`theta_paths`); a share
    ``effects`` of them with an undeclared effect on their noisy outputs
    (:func:`~jaxcal.training.data.sim_effects.add_effects`; ``x_clean`` stays clean).

    Returns:
        ``(simulated, x_clean)``: the simulated units (noisy outputs, theta labels,
        the real units' lengths; unit ids ``-1 - i``: never a file's unit) and their
        ``[U', T, S]`` noise-free outputs.

    Raises:
        ValueError: the model gives non-finite outputs on a simulated valid row
            (the message names the parameter values' range to check).
    """
    w = np.concatenate([units.w] * copies)
    lengths = np.concatenate([units.lengths] * copies)
    k_theta, k_noise = jax.random.split(key)
    if drifts is None:
        paths = theta_paths(
            k_theta,
            problem.theta_low,
            problem.theta_high,
            lengths,
            w.shape[1],
            constant_share,
        )
    else:
        paths = drift_paths(problem, drifts, lengths, w.shape[1])
    theta = paths.astype(units.x.dtype)
    mask = np.arange(w.shape[1])[None, :] < lengths[:, None]
    clean = simulate_fleet(problem, w, theta, mask).astype(units.x.dtype)
    bad = mask & ~np.all(np.isfinite(clean), axis=-1)
    if bad.any():
        u, t = np.argwhere(bad)[0]
        raise ValueError(
            f"simulating labelled units: the model gives non-finite outputs at "
            f"theta={theta[u, t].tolist()} (simulated unit {u}, row {t}) inside the "
            f"box {problem.theta_low.tolist()} .. {problem.theta_high.tolist()}; "
            "narrow the bounds or make the model finite there"
        )
    clean = np.where(mask[..., None], clean, 0.0).astype(units.x.dtype)
    noise = np.asarray(jax.random.normal(k_noise, clean.shape), clean.dtype)
    noisy = clean + (problem.noise_std.astype(clean.dtype) * noise) * mask[..., None]
    if effects:  # a share of the units with an undeclared effect on their outputs
        seed = np.asarray(jax.random.key_data(k_noise)).ravel().tolist()
        noisy, _ = add_effects(
            np.random.default_rng(seed), noisy, clean, lengths,
            np.asarray(problem.noise_std, np.float64), effects,
        )  # fmt: skip
        noisy = np.where(mask[..., None], noisy, 0.0).astype(clean.dtype)
    ids = -1 - np.arange(len(lengths), dtype=np.int64)
    return Padded(w, noisy, theta, lengths.astype(np.int32), ids), clean


def parse_noise(noise: Sequence[str], names: Sequence[str]) -> np.ndarray | None:
    """The ``[S]`` noise std of the command line's ``noise=`` (``()``: none given):
    one value per output in order, or ``name:value`` pairs naming every output.

    Raises:
        ValueError: a malformed entry, an unknown or missing output, or a value
            that is not finite and > 0.
    """
    if not noise:
        return None
    names = list(names)
    pairs = [str(v).split(":") for v in noise]
    try:
        if all(len(p) == 2 for p in pairs):
            given = {k.strip(): float(v) for k, v in pairs}
            unknown = sorted(set(given) - set(names))
            missing = [n for n in names if n not in given]
            if unknown or missing:
                raise ValueError(
                    f"noise= names unknown outputs {unknown} or misses {missing}; "
                    f"give one std per used output {names}"
                )
            values = np.array([given[n] for n in names])
        elif all(len(p) == 1 for p in pairs) and len(pairs) == len(names):
            values = np.array([float(p[0]) for p in pairs])
        else:
            raise ValueError(
                f"noise= takes one std per used output {names} (in that order) or "
                f"name:std pairs, got {list(noise)}"
            )
    except ValueError as err:
        if "noise=" in str(err):
            raise
        raise ValueError(
            f"noise=: {list(noise)} holds a value that is not a number"
        ) from None
    if not np.all(np.isfinite(values) & (values > 0)):
        raise ValueError(f"noise= values must be finite and > 0, got {values}")
    return values


def estimate_noise(problem: Problem, units: Padded) -> Problem:
    """The problem with the noise the front door's screening estimates on
    ``units`` (a UKF pass; ``noise_source`` says so)."""
    result, _ = front_ukf(problem, units)
    noise = np.asarray(result.problem.noise_std, np.float64)
    return problem.with_noise(noise, f"{result.noise_source}, on the training units")


def _joined(a: Padded, b: Padded, labels: bool = False) -> Padded:
    """Two unit sets as one (padded to the longer; labels dropped unless
    ``labels``, when both carry them)."""
    steps = max(a.w.shape[1], b.w.shape[1])

    def pad(v):
        return np.pad(v, [(0, 0), (0, steps - v.shape[1])] + [(0, 0)] * (v.ndim - 2))

    return Padded(
        np.concatenate([pad(a.w), pad(b.w)]),
        np.concatenate([pad(a.x), pad(b.x)]),
        np.concatenate([pad(a.theta), pad(b.theta)]) if labels else None,
        np.concatenate([a.lengths, b.lengths]),
        np.concatenate([a.unit_ids, b.unit_ids]),
    )


# the share of a tuned policy's guard units with an undeclared effect
GUARD_EFFECTS = 0.5


class Simulations:
    """A run's simulated units, each made on first use (module doc).

    Args:
        cfg: the run's :class:`~jaxcal.training.config.TrainConfig` (``simulate``,
            ``noise``, ``seed``).
        data: the run's :class:`~jaxcal.training.data.calibration.CalibrationData`.
        log: where notes go.
    """

    def __init__(self, cfg, data, log=print):
        self.cfg, self.data, self.log = cfg.simulate, data, log
        self.given = parse_noise(cfg.noise, data.problem.output_names)
        self.key = jax.random.fold_in(jax.random.key(cfg.seed), 27)
        self._problem: Problem | None = None
        self._train: tuple[Padded, np.ndarray] | None = None
        self._paths: tuple[Padded, np.ndarray] | None = None
        self._selection: Padded | None = None
        self.used: dict[str, str] = {}

    def problem(self) -> Problem:
        """The problem with the simulations' noise (given, else estimated)."""
        if self._problem is None:
            problem = self.data.problem
            if self.given is not None:
                problem = problem.with_noise(self.given, "given")
            else:
                self.log("simulated units need the output noise: estimating it")
                problem = estimate_noise(problem, self.data.train)
            noise = ", ".join(
                f"{n} {v:.3g}"
                for n, v in zip(problem.output_names, problem.noise_std, strict=True)
            )
            self.log(f"simulation noise ({problem.noise_source}): {noise}")
            self._problem = problem
        return self._problem

    def _train_sims(self) -> tuple[Padded, np.ndarray]:
        if self._train is None:
            self._train = simulate_units(
                self.problem(),
                self.data.train,
                jax.random.fold_in(self.key, 0),
                copies=self.cfg.copies,
                constant_share=self.cfg.constant_share,
                effects=self.cfg.effects,
            )
        return self._train

    def labelled_train(self):
        """The run's data with simulated, labelled training units (the surrogate D
        of unlabelled data is fitted on them)."""
        self.used["surrogate"] = "simulated training units"
        return self.data._replace(train=self._train_sims()[0])

    def tuning_units(self, effects: float | None = None) -> Padded:
        """Labelled units simulated as the selection units are (:meth:`
        _held_out_sims`, other draws), a share ``effects`` (default
        ``simulate.effects``) with an undeclared effect, with as many clean ones
        drawn across the box: what ``tune`` fits the actor on."""
        share = self.cfg.effects if effects is None else max(effects, self.cfg.effects)
        sim, along = self._held_out_sims(3, share)
        # and clean units drawn across the box: tuned on the data's slow drifts
        # alone, a policy loses on faster changes (guard_units checks)
        self.used["tune"] = (
            f"units simulated along {along}, and clean units with theta drawn "
            "across the box"
        )
        return _joined(sim, self._held_out_sims(5, paths="box")[0], labels=True)

    def training_fleet(self) -> tuple[Padded, np.ndarray | None]:
        """``(units, x_target)`` the policy trains on (``simulate.train``)."""
        real = self.data.train
        self.used["policy"] = {
            "data": "training units",
            "simulated": "simulated training units",
            "both": "training units and simulated ones",
        }[self.cfg.train]
        if self.cfg.train == "data":
            return real, None
        sim, clean = self._train_sims()
        if self.cfg.train == "simulated":
            return sim, clean
        return _joined(real, sim), np.concatenate([real.x, clean])

    def training_theta(self) -> np.ndarray | None:
        """``[U, T, P]`` the true theta of :meth:`training_fleet`'s rows where it
        is known (the simulated units'; NaN on the real units, whose labels, if
        any, only score), ``None`` when it trains on the data alone."""
        if self.cfg.train == "data":
            return None
        sim = self._train_sims()[0]
        if self.cfg.train == "simulated":
            return sim.theta
        unknown = np.full(self.data.train.x.shape[:2] + sim.theta.shape[2:], np.nan)
        return np.concatenate([unknown.astype(sim.theta.dtype), sim.theta])

    def _drifts(self) -> tuple[Padded, np.ndarray]:
        """``(units, drifts)``: every unit but the test ones and the theta drifts
        the UKF finds on them (:func:`estimated_drifts`), made once."""
        if self._paths is None:
            train, val = self.data.train, self.data.val
            units = train if val is None else _joined(train, val)
            self.log(
                "simulated units follow the theta drifts the UKF finds in the data"
            )
            self._paths = units, estimated_drifts(self.problem(), units)
        return self._paths

    def _held_out_sims(
        self, salt: int, effects: float = 0.0, paths: str | None = None
    ) -> tuple[Padded, str]:
        """``(simulated units, what they follow)`` for selection and the band:
        ``band_copies`` copies along the validation units' conditions (the training
        units' without them) with theta drawn across the box, or
        (``simulate.paths=data``) along every non-test unit's conditions with the
        theta drifts the UKF finds in the data, each copy of a unit with another
        unit's drift (conditions and drift: a pair the policy never trained on);
        a share ``effects`` of them with an undeclared effect on their outputs;
        ``paths`` overrides ``simulate.paths``."""
        key = jax.random.fold_in(self.key, salt)
        copies = self.cfg.band_copies
        if (paths or self.cfg.paths) == "data":
            units, drifts = self._drifts()
            turn = np.arange(units.w.shape[0])[None] + np.arange(copies)[:, None] + 1
            drifts = drifts[(turn % len(drifts)).ravel()]  # copy c, unit u: u + c + 1
            sim, _ = simulate_units(
                self.problem(), units, key, copies=copies, drifts=drifts,
                effects=effects,
            )  # fmt: skip
            what = "the training and validation units' conditions, each with another's"
            return sim, f"{what} theta drift"
        val = self.data.val
        base, which = (val, "validation") if val is not None else (None, "training")
        base = self.data.train if base is None else base
        sim, _ = simulate_units(
            self.problem(),
            base,
            key,
            copies=copies,
            constant_share=self.cfg.constant_share,
            effects=effects,
        )
        return sim, f"the {which} units' conditions"

    def selection_units(self, clean: bool = False) -> Padded:
        """Simulated units (:meth:`_held_out_sims`) on which
        ``budget.select=sim_theta`` scores theta; with ``simulate.effects`` the
        same share of them carries an undeclared effect, so that the policy kept
        is the one that holds under model error too (the band's units stay
        clean). ``clean``: the same units without their effects (the same
        object when there are none)."""
        if clean and not self.cfg.effects:
            return self.selection_units()
        if clean:
            return self._held_out_sims(2)[0]
        if self._selection is not None:
            return self._selection
        sim, _ = self._held_out_sims(2, self.cfg.effects)
        self._selection = sim
        self.used["selection"] = "theta RMSE on simulated units" + (
            f", a share {self.cfg.effects:g} with an undeclared effect"
            if self.cfg.effects
            else ""
        )
        return sim

    def guard_units(self) -> list[Padded]:
        """Simulated units a tuned policy may not lose accuracy on: the selection
        units without their effects; units with theta drawn across the box
        (faster, larger changes than the data's drifts: a policy tuned to sit
        still under a sensor drift must still follow a parameter's); and units
        with an undeclared effect in half of them (a policy tuned on clean units
        must not lose what the filter's adaptive noise holds under a bias)."""
        box, _ = self._held_out_sims(4, paths="box")
        effects, _ = self._held_out_sims(6, max(self.cfg.effects, GUARD_EFFECTS))
        return [self.selection_units(clean=True), box, effects]

    def band_units(self) -> tuple[Padded | None, str]:
        """``(units, what they are)`` the uncertainty band is fitted on
        (``simulate.band``)."""
        val = self.data.val
        labelled = val is not None and val.theta is not None
        if self.cfg.band == "labelled" or (self.cfg.band == "auto" and labelled):
            self.used["band"] = "labelled validation units"
            return val, "labelled validation units"
        sim, along = self._held_out_sims(1)
        what = f"units simulated along {along}"
        self.used["band"] = what
        return sim, what

    def with_noise_floor(self, cfg):
        """``cfg`` with the log cost's floor at the noise (``simulate.cost_floor=
        noise``): the RMS of the noise std in the cost's normalised units, here each
        output's float64 spread over the training units
        (:func:`~jaxcal.training.data.calibration.output_spread`, as it always was;
        the run's normalisation, in the run's dtype, differs from it in the last
        digits). Below the noise a simulated target's error is no longer worth a
        log-scale reward: a floor of 1e-4 made the policy trade the noise averaging
        of the steady state for speed (``results/policy_any_model``)."""
        if self.cfg.train == "data" or self.cfg.cost_floor != "noise":
            return cfg
        spread = output_spread(self.data.train)
        floor = float(np.sqrt(np.mean((self.problem().noise_std / spread) ** 2)))

        self.used["cost_floor"] = f"{floor:.3g}"
        return dataclasses.replace(
            cfg, env=dataclasses.replace(cfg.env, cost_floor=floor)
        )

    def report(self) -> dict:
        """The ``final.json`` record: what was simulated, with which noise."""
        if self._problem is None:
            return {"used_for": self.used}
        return {
            "used_for": self.used,
            "noise_std": dict(
                zip(
                    self._problem.output_names,
                    self._problem.noise_std.tolist(),
                    strict=True,
                )
            ),
            "noise_source": self._problem.noise_source,
            "copies": self.cfg.copies,
            "constant_share": self.cfg.constant_share,
        }
