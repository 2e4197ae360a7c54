"""The fallback when no library effect explains the residual: a discrepancy delta(w).

Kennedy & O'Hagan (2001) write the data as ``x_t = F(w_t, theta) + delta(w_t)`` (paper
eq. cal2). Here ``delta_s`` is, per sensor, a ridge regression on the monomials (up to
degree 3) of the standardised operating conditions (the model's ``W``), a smooth
regressor that is fitted in closed form and cross-validated exactly. Degree and ridge
strength are chosen per sensor by K-fold cross-validation with folds grouped by unit
(contiguous blocks of rows when there are fewer units than folds), so no unit is seen
both in training and validation.

A sensor's delta is *significant* when its cross-validated reduction of the normalised
SSR (an out-of-sample gain) exceeds ``margin + 3 sqrt(2 df)``, ``df`` the trace of the
ridge hat matrix. On a pure-noise residual the CV gain is about ``-df`` with a spread of
about ``sqrt(2 df)``. Over 520 pure-noise sensor fits at N = 470 rows (degree and ridge
selected as here) the 99.9 % quantile of the gain was 14.8 and its maximum 17.8, while
the threshold is at least 17.2 (``df`` about 3): about one false alarm per thousand
sensors.

What delta depends on is reported as shares of its CV gain: ``dependence["constant"]``
is the gain of an offset alone, ``dependence[input]`` what delta fitted on that input
(and the offset) gains on top of the offset, and ``unique[input]`` the gain lost when
that input is dropped from the full delta (ablation). With discrete operating conditions
(C-MAPSS FD002) the inputs are redundant, so ``unique`` is near zero for all of them and
``dependence`` is the informative one.

Coloured noise: when the residual's noise is serially correlated (an AR(p) model per
output, :mod:`jaxcal.diagnosis.residuals.noise`), the regression is generalised least
squares, the response and the design whitened per output (``whiten``), so the
cross-validated gain and its threshold are those of independent rows.
"""

from __future__ import annotations

import dataclasses
import functools
import itertools
from collections.abc import Sequence
from typing import NamedTuple

import numpy as np


@dataclasses.dataclass(frozen=True)
class DiscrepancyConfig:
    """Static settings of :func:`fit_discrepancy`."""

    degrees: tuple[int, ...] = (1, 2, 3)  # polynomial degrees tried
    ridges: tuple[float, ...] = (1e-6, 1e-4, 1e-2, 1.0)  # ridge strength per row
    folds: int = 5  # cross-validation folds
    margin: float = 10.0  # added to 3 sqrt(2 df) in the significance threshold
    backfit_rounds: int = 2  # delta <-> theta alternations in the pipeline

    def __post_init__(self):
        if self.folds < 2 or not self.degrees or not self.ridges:
            raise ValueError("DiscrepancyConfig: need folds >= 2, degrees and ridges")


class SensorDiscrepancy(NamedTuple):
    """The fitted delta of one sensor (normalised units: multiples of its noise std)."""

    sensor: str
    significant: bool
    degree: int
    ridge: float
    df: float  # effective degrees of freedom (trace of the hat matrix)
    cv_gain: float  # SSR reduction out of sample, normalised units
    threshold: float  # margin + 3 sqrt(2 df)
    dependence: dict  # "constant" / input -> CV gain of an offset / added by the input
    unique: dict  # input -> CV gain lost when that input is dropped, as a share
    amplitude: float  # std of delta over the rows, normalised units
    mean: float  # mean of delta over the rows, normalised units


class Discrepancy(NamedTuple):
    """A delta(w) for every sensor; :func:`predict_discrepancy` evaluates it."""

    sensors: tuple[SensorDiscrepancy, ...]
    coef: tuple[np.ndarray, ...]  # per sensor, monomial coefficients
    inputs: tuple[int, ...]  # columns of w that vary (the others are dropped)
    w_mean: np.ndarray  # [W]
    w_std: np.ndarray  # [W]

    @property
    def any_significant(self) -> bool:
        """True when delta is significant for at least one sensor."""
        return any(s.significant for s in self.sensors)


def _monomials(z: np.ndarray, degree: int) -> np.ndarray:
    """``[N, F]`` all monomials of the columns of ``z`` up to ``degree`` (with 1)."""
    cols = [np.ones(z.shape[0])]
    for d in range(1, degree + 1):
        for combo in itertools.combinations_with_replacement(range(z.shape[1]), d):
            cols.append(np.prod(z[:, list(combo)], axis=1))
    return np.stack(cols, axis=1)


def _ridge(phi, y, ridge, *, with_df: bool = True, products=None):
    """Ridge solution (intercept unpenalised) for all columns of ``y`` and its df
    (``None`` without ``with_df``: cross-validation needs only the solution).
    ``products``: ``(phi^T phi, phi^T y, rows)`` when already computed (they do not
    depend on the strength, so a cross-validation fold computes them once for all;
    ``phi`` is then not read)."""
    gram0, rhs, rows = (
        (phi.T @ phi, phi.T @ y, phi.shape[0]) if products is None else products
    )
    pen = ridge * rows * np.eye(gram0.shape[0])
    pen[0, 0] = 0.0
    gram_inv = np.linalg.pinv(gram0 + pen, hermitian=True)
    df = float(np.sum(gram_inv * gram0)) if with_df else None
    return gram_inv @ rhs, df


def _folds(groups: np.ndarray, num_folds: int) -> np.ndarray:
    """Fold id per row: whole units when there are enough, else contiguous blocks."""
    ids = np.unique(groups)
    if ids.size >= num_folds:
        return np.searchsorted(ids, groups) % num_folds
    return np.minimum(
        (np.arange(groups.size) * num_folds) // groups.size, num_folds - 1
    )


def _cv_sse(z, y, folds, degree, ridges, whiten=None) -> np.ndarray:
    """``[R, S]`` cross-validated sums of squared errors, one row per strength of
    ``ridges`` (of the whitened rows when ``whiten`` is given: per-output designs,
    generalised least squares)."""
    sse = np.zeros((len(ridges), y.shape[1]))
    design = _designs(z, degree, y.shape[1], whiten)
    yw = y if whiten is None else whiten(y)
    masks = [folds == f for f in np.unique(folds)]
    for s, phi in design:
        cols = slice(None) if s is None else [s]
        # each fold's rows and products once; a fold's training products are the
        # sum of the other folds' (not a copy of every other row per fold)
        parts = [(phi[m], yw[m][:, cols]) for m in masks]
        prods = [(p.T @ p, p.T @ t) for p, t in parts]
        for f, (phi_test, y_test) in enumerate(parts):
            others = [prods[g] for g in range(len(parts)) if g != f]
            products = (sum(g for g, _ in others), sum(r for _, r in others),
                        phi.shape[0] - phi_test.shape[0])  # fmt: skip
            for i, ridge in enumerate(ridges):
                coef, _ = _ridge(None, None, ridge, with_df=False, products=products)
                err = y_test - phi_test @ coef
                sse[i, cols] += np.sum(err**2, axis=0)
    return sse


def _designs(z, degree, num_s, whiten):
    """``(output or None, design [N, F])``: one shared design, or one whitened
    design per output of ``whiten`` (``num_s`` of them), each made when read (a
    fleet's rows times every output and monomial at once was the diagnosis's peak
    of memory; each output is whitened on its own, so the same numbers)."""
    if whiten is None:
        yield None, _monomials(z, degree)
        return
    for s in range(num_s):
        yield s, _design(z, degree, whiten if num_s == 1 else _one_output(whiten, s))


def _design(z, degree, whiten):
    """``[N, F]`` the monomials, whitened as the rows of ``whiten``'s one output
    (``None``: as they are)."""
    phi = _monomials(z, degree)
    return phi if whiten is None else whiten(phi[:, None, :])[:, 0]


def _standardised_inputs(w: np.ndarray):
    """``(mean [W], std [W], the varying conditions' columns, their standardised
    values [N, W_varying])``: a constant condition explains nothing."""
    w_mean, w_std = w.mean(0), w.std(0)
    inputs = tuple(
        j for j in range(w.shape[1]) if w_std[j] > 1e-9 * max(abs(w_mean[j]), 1)
    )
    z = (w[:, inputs] - w_mean[list(inputs)]) / w_std[list(inputs)]
    return w_mean, w_std, inputs, z


def _gain_shares(sub, names, degree: int, base, full, gain: float):
    """What the CV gain of an output's delta depends on: ``(dependence, unique)``.

    Args:
        sub: ``sub(columns, degree) -> CV SSE`` of the output on some inputs.
        names: the inputs' condition names; degree: the selected degree.
        base: SSR without delta; full: CV SSE of the selected delta; gain: its gain.

    Returns:
        ``dependence``: the share of an offset only (``constant``) and of each input
        alone on top of it; ``unique``: the share lost when an input is dropped.
    """
    const = sub([], 0)
    # shares in [0, 1]: a sub-model's CV gain can exceed the selected full model's by
    # the noise of cross-validation, which is no share above 1
    dependence = {"constant": min(max(float(base - const), 0.0) / gain, 1.0)}
    unique = {}
    for k, name in enumerate(names):
        alone = sub([k], degree)
        dependence[name] = min(max(float(const - alone), 0.0) / gain, 1.0)
        keep = [i for i in range(len(names)) if i != k]
        loss = sub(keep, degree) - full
        unique[name] = min(max(float(loss), 0.0) / gain, 1.0)
    return dependence, unique


def fit_discrepancy(
    w: np.ndarray,
    resid: np.ndarray,
    groups: np.ndarray,
    sensor_names: Sequence[str],
    cfg: DiscrepancyConfig,
    condition_names: Sequence[str] | None = None,
    whiten=None,
) -> Discrepancy:
    """Fit and test ``delta_s(w)`` to a normalised residual.

    Args:
        w: ``[N, W]`` operating conditions.
        resid: ``[N, S]`` normalised residual (multiples of each sensor's noise std).
        groups: ``[N]`` unit of each row (cross-validation groups).
        sensor_names: ``S`` names.
        cfg: settings.
        condition_names: ``W`` names of the conditions in ``dependence`` / ``unique``
            (default ``w[0]``, ``w[1]``, ...).
        whiten: ``whiten(arr, outputs=None)``, the prewhitening of normalised
            arrays ``[N, S, ...]`` along rows, or of ``[N, len(outputs), ...]``
            holding those outputs alone (``None``: the noise is white).

    Returns:
        :class:`Discrepancy`, one entry per sensor.
    """
    if condition_names is None:
        condition_names = [f"w[{j}]" for j in range(w.shape[1])]
    if len(condition_names) != w.shape[1]:
        raise ValueError(
            f"condition_names has {len(condition_names)} names for w [N, {w.shape[1]}]"
        )
    w_mean, w_std, inputs, z = _standardised_inputs(w)
    folds = _folds(groups, cfg.folds)
    degrees = cfg.degrees if inputs else (0,)
    grid = [(d, r) for d in degrees for r in cfg.ridges]
    cv = np.concatenate(
        [_cv_sse(z, resid, folds, d, cfg.ridges, whiten) for d in degrees]
    )  # [len(grid), S], the grid's order
    white = resid if whiten is None else whiten(resid)
    base = np.sum(white**2, axis=0)
    sensors, coefs = [], []
    for s, name in enumerate(sensor_names):
        d, r = grid[int(np.argmin(cv[:, s]))]
        one = None if whiten is None else _one_output(whiten, s)
        coef, df = _ridge(_design(z, d, one), white[:, s], r)
        gain = float(base[s] - cv[:, s].min())
        threshold = cfg.margin + 3.0 * np.sqrt(2.0 * df)
        delta = _monomials(z, d) @ coef
        dependence, unique = {}, {}
        if gain > threshold:

            def sub(cols, degree, s=s, r=r):  # CV SSE of output s on some inputs
                part = None if whiten is None else _one_output(whiten, s)
                sse = _cv_sse(z[:, cols], resid[:, [s]], folds, degree, [r], part)
                return sse[0, 0]

            names = [condition_names[j] for j in inputs]
            dependence, unique = _gain_shares(
                sub, names, d, base[s], cv[:, s].min(), gain
            )
        sensors.append(
            SensorDiscrepancy(
                name,
                bool(gain > threshold),
                d,
                r,
                df,
                gain,
                threshold,
                dependence,
                unique,
                float(delta.std()),
                float(delta.mean()),
            )
        )
        coefs.append(coef)
    return Discrepancy(tuple(sensors), tuple(coefs), inputs, w_mean, w_std)


def _one_output(whiten, s: int):
    """``whiten`` of output ``s`` alone, for arrays ``[N, 1, ...]`` (each output is
    whitened on its own: the other outputs' rows are not computed)."""
    return functools.partial(whiten, outputs=[s])


def predict_discrepancy(disc: Discrepancy, w: np.ndarray) -> np.ndarray:
    """``[N, S]`` delta(w) in normalised units (zero for non-significant sensors)."""
    idx = list(disc.inputs)
    z = (w[:, idx] - disc.w_mean[idx]) / disc.w_std[idx]
    out = np.zeros((w.shape[0], len(disc.sensors)))
    for s, (sd, coef) in enumerate(zip(disc.sensors, disc.coef, strict=True)):
        if sd.significant:
            out[:, s] = _monomials(z, sd.degree) @ coef
    return out
