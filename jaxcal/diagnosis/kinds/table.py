"""The one table of effect kinds the diagnosis knows, and the candidates built from it.

An effect the model lacks is described by three independent choices:

* a **channel**, where it enters the model: a ``parameter`` of the model (moved from
  its nominal value), a registered ``effect`` input (``model.effects``), a logged
  ``condition`` read with an offset (the model sees ``w + offset``), or the
  measurement layer, ``additive`` (``y = x + a``) or ``multiplicative``
  (``y = x (1 + m)``) on one output;
* a **profile** in time within a unit: ``constant``, ``drift`` (grows linearly with
  ``tau``, the time since the unit's first row per :data:`TAU_CYCLES` steps),
  ``step`` (zero before an onset, constant from it on; the onset is estimated per
  unit) or ``spline`` (a smooth per-unit function of time, :data:`candidate knots
  <jaxcal.diagnosis.data.prepare.LoopData>`);
* a **form**: ``fleet`` (one value shared by every unit) or ``units`` (a value per
  unit, on the units that carry it; which units is chosen by the same criterion as
  everything else, :mod:`jaxcal.diagnosis.fitting.screen`).

:class:`EffectKind` holds the rest of what a kind means: its natural step (the size
of one fitted unit), its physical unit, the plausibility rules that apply to it
(:mod:`jaxcal.diagnosis.report.plausibility`) and how a study draws its size
(:mod:`jaxcal.diagnosis.data.synthetic`). :data:`KINDS` is the table; a new kind is
one new entry.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from jaxcal.model import Model

TAU_CYCLES = 100.0  # drift unit: per 100 time steps since the unit's first row
DEFAULT_SCALE_FRACTION = 0.01  # natural step: 1 % of a parameter's bound range
CHANNELS = ("parameter", "effect", "condition", "additive", "multiplicative")
PROFILES = ("constant", "drift", "step", "spline")
FORMS = ("fleet", "units")


@dataclasses.dataclass(frozen=True)
class EffectKind:
    """One kind of effect (module docstring).

    Attributes:
        name: the kind's name (``sensor_bias``); candidates are named
            ``<name>[<target>]`` (a registered effect by its own name).
        channel: one of :data:`CHANNELS`.
        profile: one of :data:`PROFILES`.
        fleet: True when the kind has a fleet-wide form; a spline or a step is per
            unit by nature (each unit its own trajectory or onset).
        rules: plausibility rules (:data:`jaxcal.diagnosis.report.plausibility.FLAGS`)
            that apply.
        size_range: the default magnitude range of a study's drawn size
            (:mod:`jaxcal.diagnosis.data.synthetic`): in natural steps of the target
            (parameter, effect), in the output's noise std (additive), in it relative
            to the output's mean level (multiplicative) or in % of the condition's std.
        min_effect: the smallest size a unit must show to be listed as carrying it,
            in natural steps (:mod:`jaxcal.diagnosis.report.units`). A parameter's is
            half a step: its per-unit size is its change over the record, and a free
            parameter absorbs the declared ones' mismatch as a slow change of a few
            tenths of a step in every unit. The other kinds' is a tenth.
    """

    name: str
    channel: str
    profile: str
    fleet: bool
    rules: tuple[str, ...] = ()
    size_range: tuple[float, float] = (2.0, 5.0)
    min_effect: float = 0.1

    def __post_init__(self):
        if self.channel not in CHANNELS or self.profile not in PROFILES:
            raise ValueError(f"{self.name}: bad channel or profile")

    @property
    def forms(self) -> tuple[str, ...]:
        """The forms a candidate of this kind may take."""
        return FORMS if self.fleet else ("units",)

    @property
    def is_sensor(self) -> bool:
        """True for the measurement layer (outside the model's dynamics)."""
        return self.channel in ("additive", "multiplicative")

    def num_free(self, num_knots: int) -> int:
        """Free parameters of one unit's (or the fleet's) term: its coefficients
        (``num_knots`` for a spline, else one) and, for a step, the onset."""
        return (num_knots if self.profile == "spline" else 1) + (self.profile == "step")

    def candidate_name(self, target: str) -> str:
        """Display name of the candidate on ``target``."""
        return target if self.channel == "effect" else f"{self.name}[{target}]"

    def study_kind(self, target: str) -> str:
        """The label a study groups records by (a registered effect: its name)."""
        return target if self.channel == "effect" else self.name

    def targets(
        self, model: Model, outputs: Sequence[str], declared: Sequence[str]
    ) -> tuple[str, ...]:
        """What a candidate of this kind can act on for ``model``."""
        if self.channel == "parameter":
            return tuple(p for p in model.parameter_names if p not in declared)
        if self.channel == "effect":
            return tuple(e.name for e in model.effects)
        if self.channel == "condition":
            return offset_conditions(model)
        return tuple(outputs)

    def physical_unit(self, model: Model, target: str) -> str:
        """The unit of the fitted size (the model's vocabulary)."""
        per = f" per {TAU_CYCLES:g} cycles" if self.profile == "drift" else ""
        if self.channel == "multiplicative":
            return "-" + per
        if self.channel == "effect":
            return next(e.unit for e in model.effects if e.name == target) + per
        return model.unit_of(target) + per


def _kinds(*kinds: EffectKind) -> dict[str, EffectKind]:
    return {k.name: k for k in kinds}


KINDS: dict[str, EffectKind] = _kinds(
    EffectKind(
        "parameter", "parameter", "spline", False,
        ("outside_bounds", "better_than_new", "constant_from_start"), (0.5, 2.0),
        min_effect=0.5,
    ),
    EffectKind(
        "parameter_step", "parameter", "step", False,
        ("outside_bounds", "better_than_new"), (0.5, 2.0), min_effect=0.5,
    ),
    EffectKind("effect", "effect", "constant", True, ("outside_bounds",), (0.5, 2.0)),
    EffectKind("condition_offset", "condition", "constant", True, (), (0.5, 2.0)),
    EffectKind("sensor_bias", "additive", "constant", True),
    EffectKind("sensor_gain", "multiplicative", "constant", True),
    EffectKind("sensor_drift", "additive", "drift", True, size_range=(3.0, 6.0)),
    EffectKind(
        "sensor_gain_drift", "multiplicative", "drift", True, size_range=(3.0, 6.0)
    ),
    EffectKind("sensor_step", "additive", "step", False),
)  # fmt: skip


def natural_scale(model: Model, name: str) -> float:
    """Size of one fitted unit of a parameter or registered effect ``name``:
    ``DiagnosisHints.scales`` when given, else 1 % of its bound range."""
    scales = model.diagnosis.scales or {}
    if name in scales:
        return float(scales[name])
    for p in (*model.parameters, *model.effects):
        if p.name == name:
            return DEFAULT_SCALE_FRACTION * (p.high - p.low)
    raise ValueError(f"model {model.name!r} has no parameter or effect {name!r}")


def offset_conditions(model: Model) -> tuple[str, ...]:
    """The conditions that may carry a constant offset (generic candidates)."""
    allowed = model.diagnosis.offset_conditions
    return model.condition_names if allowed is None else tuple(allowed)


def kinds_for(
    model: Model, names: Sequence[str] | None = None
) -> tuple[EffectKind, ...]:
    """The kinds of :data:`KINDS` that apply to ``model`` (a model with memory has no
    registered-effect channel), restricted to ``names`` when given."""
    if names:
        unknown = sorted(set(names) - set(KINDS))
        if unknown:
            raise ValueError(
                f"unknown effect kinds {unknown}; valid: {', '.join(KINDS)}"
            )
    out = []
    for kind in KINDS.values():
        if names and kind.name not in names:
            continue
        if kind.channel == "effect" and (model.is_stateful or not model.effects):
            continue
        if kind.channel == "condition" and not offset_conditions(model):
            continue
        out.append(kind)
    return tuple(out)


@dataclasses.dataclass(frozen=True)
class Candidate:
    """One candidate effect: a kind on a target, in a form.

    Attributes:
        kind: its :class:`EffectKind`.
        target: the parameter, registered effect, condition or output it acts on.
        scale: physical size of one unit of a fitted coefficient (natural step).
        unit: physical unit of the size.
        form: ``fleet`` or ``units``.
        carriers: unit positions that carry it (``units`` form; empty: none chosen).
        onsets: a step's onset per carrier, as a row index into the data.
    """

    kind: EffectKind
    target: str
    scale: float
    unit: str
    form: str = "fleet"
    carriers: tuple[int, ...] = ()
    onsets: tuple[int, ...] = ()

    @property
    def name(self) -> str:
        """Display name, e.g. ``sensor_bias[T30]`` (the form is in :attr:`label`)."""
        return self.kind.candidate_name(self.target)

    @property
    def key(self) -> str:
        """Unique per name and form (a name may be tried in both forms)."""
        return f"{self.name}|{self.form}"

    @property
    def label(self) -> str:
        """The name with its form: ``sensor_bias[T30]`` or ``... in 2 units``."""
        if self.form == "fleet":
            return self.name
        return f"{self.name} in {len(self.carriers)} unit(s)"

    @property
    def family(self) -> str:
        """The kind's name."""
        return self.kind.name

    @property
    def per_unit(self) -> bool:
        """True in the ``units`` form."""
        return self.form == "units"

    def with_form(
        self, form: str, carriers: Sequence[int] = (), onsets: Sequence[int] = ()
    ) -> Candidate:
        """The same effect in another form."""
        if form not in self.kind.forms:
            raise ValueError(f"{self.name} has no {form!r} form")
        return dataclasses.replace(
            self,
            form=form,
            carriers=tuple(int(c) for c in carriers),
            onsets=tuple(int(o) for o in onsets),
        )


def nests(general: Candidate, special: Candidate) -> bool:
    """True when ``special`` is ``general`` at the edge of its parameters (a step from
    a unit's first row is a bias): the two are not rival explanations, and the
    simpler one stands (parsimony), so they are never reported as confounded."""
    return (
        general.target == special.target
        and general.kind.channel == special.kind.channel
        and general.kind.profile == "step"
        and special.kind.profile == "constant"
    )


def build_library(
    model: Model,
    declared: Sequence[str],
    sensor_names: Sequence[str],
    noise_std: np.ndarray,
    sensor_mean_abs: np.ndarray,
    condition_scale: np.ndarray | None = None,
    *,
    kinds: Sequence[str] | None = None,
) -> tuple[Candidate, ...]:
    """Every candidate effect of ``model`` for a data set, in the table's order (the
    ``units`` form's carriers are chosen later, by the screen).

    Args:
        model: the model (its parameters, effects, conditions and units).
        declared: the calibrated parameters; they are not candidates.
        sensor_names: the ``S`` outputs of the residual.
        noise_std: ``[S]`` noise std per output (the measurement layer's scales).
        sensor_mean_abs: ``[S]`` mean ``|x_s|`` (scale of a gain).
        condition_scale: ``[W]`` natural size of a condition offset (default 1).
        kinds: restrict to these kinds (``None``: every kind that applies).
    """
    out = []
    for kind in kinds_for(model, kinds):
        for target in kind.targets(model, sensor_names, declared):
            if kind.channel in ("parameter", "effect"):
                scale = natural_scale(model, target)
            elif kind.channel == "condition":
                j = model.condition_names.index(target)
                scale = 1.0 if condition_scale is None else float(condition_scale[j])
            else:
                s = list(sensor_names).index(target)
                scale = float(noise_std[s])
                if kind.channel == "multiplicative":
                    scale /= max(float(sensor_mean_abs[s]), 1e-12)
            form = "fleet" if kind.fleet else "units"
            out.append(
                Candidate(kind, target, scale, kind.physical_unit(model, target), form)
            )
    return tuple(out)
