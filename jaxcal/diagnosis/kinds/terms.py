"""What a fit moves: the declared parameters and the candidate terms, as columns.

A :class:`ModelSpec` names the declared parameters (a B-spline in time per unit,
:mod:`jaxcal.diagnosis.data.prepare`), for a model with memory an offset of each unit's
initial state, and the candidate effects (:mod:`jaxcal.diagnosis.kinds.table`: a
``fleet`` term has one coefficient shared by all units, a ``units`` term one, or ``Kc``
for a smoothly changing parameter, per carrying unit). Every coefficient moves one
channel of the extended model along its profile in time: a
:class:`~jaxcal.diagnosis.kinds.signatures.Tangent`. :func:`layout` lists them, local
(per unit) first, then shared; :func:`model_inputs` turns coefficients into the
extended model's row inputs; :func:`num_params` and :func:`selection_penalty` are what
the extended BIC charges for them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence
from typing import NamedTuple

import jax.numpy as jnp
import numpy as np
from scipy.special import gammaln

from jaxcal.diagnosis.data.prepare import LoopData
from jaxcal.diagnosis.kinds.signatures import RowInputs, Tangent, zero_inputs
from jaxcal.diagnosis.kinds.table import Candidate, natural_scale
from jaxcal.model import Model

STATE_STEP = 0.01  # natural step of an initial-state offset: 1 % of the state's size


@dataclasses.dataclass(frozen=True)
class ModelSpec:
    """What a fit moves.

    Attributes:
        declared: the declared parameters, fitted per unit as splines.
        terms: candidate effects (each in its form,
        :class:`~jaxcal.diagnosis.kinds.table.Candidate`).
        initial_state: a model with memory: fit an offset of each unit's initial
            state (its data may not start where the model's ``init`` puts it).
    """

    declared: tuple[str, ...]
    terms: tuple[Candidate, ...] = ()
    initial_state: bool = False

    @property
    def unit_terms(self) -> tuple[Candidate, ...]:
        """Terms with per-unit coefficients (``units`` form)."""
        return tuple(c for c in self.terms if c.per_unit)

    @property
    def global_terms(self) -> tuple[Candidate, ...]:
        """Terms with one shared coefficient (``fleet`` form)."""
        return tuple(c for c in self.terms if not c.per_unit)

    @property
    def unit_params(self) -> tuple[str, ...]:
        """Model parameters with a per-unit trajectory: declared, then the
        parameter-channel terms."""
        extra = [c.target for c in self.terms if c.kind.channel == "parameter"]
        return self.declared + tuple(t for t in extra if t not in self.declared)

    def with_terms(self, terms: Sequence[Candidate]) -> ModelSpec:
        """The same spec with other terms."""
        return dataclasses.replace(self, terms=tuple(terms))


class Block(NamedTuple):
    """A block of coefficients: ``local`` (per unit) or shared."""

    role: str  # "declared", "state" or "term"
    name: str  # parameter / state name, or the term's key
    columns: slice  # within the local or the global part
    local: bool


class Layout(NamedTuple):
    """The columns of a spec on a data set: local (per unit) first, then shared."""

    tangents: list[Tangent]
    blocks: list[Block]
    num_local: int
    num_global: int


def term_profile(data: LoopData, cand: Candidate) -> np.ndarray:
    """``[N, k]`` amount of the term's channel per unit of each coefficient (the
    natural step included); zero on the rows of units that do not carry it."""
    kind = cand.kind
    if kind.profile == "spline":
        prof = data.basis_candidate.copy()
    elif kind.profile == "drift":
        prof = data.tau[:, None].copy()
    elif kind.profile == "step":
        onset = np.full(data.num_units, np.iinfo(np.int64).max)
        for u, row in zip(cand.carriers, cand.onsets, strict=True):
            onset[u] = row
        prof = (np.arange(data.num_rows) >= onset[data.unit]).astype(float)[:, None]
    else:
        prof = np.ones((data.num_rows, 1))
    if cand.per_unit:
        carries = np.zeros(data.num_units, bool)
        carries[list(cand.carriers)] = True
        prof = prof * carries[data.unit][:, None]
    return cand.scale * prof


def channel_index(model: Model, cand: Candidate) -> int:
    """The index of ``cand``'s target among its channel's (parameters, effects,
    conditions or outputs)."""
    channel = cand.kind.channel
    if channel == "parameter":
        return model.parameter_names.index(cand.target)
    if channel == "effect":
        return [e.name for e in model.effects].index(cand.target)
    if channel == "condition":
        return model.condition_names.index(cand.target)
    return model.output_index([cand.target])[0]


def state_scale(model: Model, data: LoopData) -> np.ndarray:
    """``[Z]`` natural step of each initial-state offset: :data:`STATE_STEP` of the
    state's size at the nominal parameters and the data's mean conditions."""
    z0 = np.abs(
        np.asarray(model.init_state(jnp.asarray(data.w.mean(0)), model.nominal))
    ).reshape(-1)
    return STATE_STEP * np.where(np.isfinite(z0) & (z0 > 0), z0, 1.0)


def layout(model: Model, data: LoopData, spec: ModelSpec) -> Layout:
    """Columns of ``spec`` (the coefficient order of :class:`ModelParams`)."""
    tangents, blocks = [], []

    def add(role, name, local, items):
        width = sum(
            b.columns.stop - b.columns.start for b in blocks if b.local == local
        )
        blocks.append(Block(role, name, slice(width, width + len(items)), local))
        tangents.extend(items)

    for name in spec.declared:
        j, step = model.parameter_names.index(name), natural_scale(model, name)
        add("declared", name, True,
            [Tangent("parameter", j, step * b) for b in data.basis.T])  # fmt: skip
    if spec.initial_state and model.is_stateful:
        scale = state_scale(model, data)
        for j, state in enumerate(model.state_names):
            add("state", state, True,
                [Tangent("state", j, np.full(data.num_rows, scale[j]))])  # fmt: skip
    for local in (True, False):
        for cand in spec.terms:
            if cand.per_unit != local:
                continue
            channel, idx = cand.kind.channel, channel_index(model, cand)
            prof = term_profile(data, cand)
            add("term", cand.key, local,
                [Tangent(channel, idx, p) for p in prof.T])  # fmt: skip
    num_local = sum(b.columns.stop - b.columns.start for b in blocks if b.local)
    return Layout(tangents, blocks, num_local, len(tangents) - num_local)


def num_params(data: LoopData, spec: ModelSpec, model: Model) -> int:
    """Fitted parameters: every unit's declared splines (and initial states), each
    carrier's coefficients of a units term (and a step's onset), a fleet term's one."""
    k = len(spec.declared) * data.num_knots
    if spec.initial_state and model.is_stateful:
        k += len(model.states)
    total = data.num_units * k
    for cand in spec.terms:
        per = cand.kind.num_free(data.num_candidate_knots)
        total += per * (len(cand.carriers) if cand.per_unit else 1)
    return total


def selection_penalty(data: LoopData, spec: ModelSpec) -> float:
    """``2 ln C(U, |C|)`` per units term: the extended BIC's price of choosing which
    units carry it (Chen & Chen 2008, gamma = 1)."""
    u = data.num_units
    out = 0.0
    for cand in spec.unit_terms:
        m = len(cand.carriers)
        out += 2.0 * float(gammaln(u + 1) - gammaln(m + 1) - gammaln(u - m + 1))
    return out


class ModelParams(NamedTuple):
    """Fitted coefficients in natural steps."""

    unit_coef: np.ndarray  # [U, L] local columns
    global_coef: np.ndarray  # [G]


def zero_params(data: LoopData, lay: Layout) -> ModelParams:
    """All coefficients zero (nominal parameters, no effect)."""
    return ModelParams(
        np.zeros((data.num_units, lay.num_local)), np.zeros(lay.num_global)
    )


def model_inputs(
    model: Model, data: LoopData, lay: Layout, params: ModelParams
) -> RowInputs:
    """The extended model's row inputs at ``params``."""
    inputs = zero_inputs(model, data.num_rows, data.num_units)
    field = {"parameter": inputs.theta, "effect": inputs.effects,
             "condition": inputs.w_offset, "additive": inputs.additive,
             "multiplicative": inputs.multiplicative}  # fmt: skip
    first = data.starts[:-1]
    coef = [params.unit_coef[data.unit, c] for c in range(lay.num_local)]
    coef += list(params.global_coef)
    for tan, a in zip(lay.tangents, coef, strict=True):
        if tan.channel == "state":
            inputs.z0[:, tan.index] += np.asarray(a)[first] * tan.profile[first]
        else:
            field[tan.channel][:, tan.index] += a * tan.profile
    return inputs
