"""The one model protocol every layer of jaxcal speaks: :class:`Model`.

A physics model maps operating conditions ``w [W]`` and parameters ``theta [P]`` to
outputs ``x [S]``. Statically, ``x = F(w, theta)``; with memory, a hidden state
``z [Z]`` is carried: ``(z', x) = step(z, w, theta)``, ``z_0 = init_state(w_0,
theta)``. A static model is the stateful one with no state (``Z = 0``), so every
layer handles both through :meth:`Model.step` (:meth:`Model.evaluate`: ``F``).

A ``Model`` is a frozen container of names, units, bounds and pure functions (the
dynamax pattern: a model is a params container plus pure functions), hashable by
identity so it can be closed over or passed as a static argument of ``jax.jit``::

    import jaxcal

    def fn(w, theta):                      # pure JAX: w [2], theta [1] -> x [2]
        return jnp.stack([w[0] * theta[0], w[1] + theta[0]])

    model = jaxcal.Model.from_function(
        fn, conditions=("a", "b"), parameters={"p": (1.0, 0.5, 2.0)},
        outputs=("y1", "y2"))
    x, info = model.evaluate(w, theta)     # info.valid: finite and in range

Optional hooks: ``condition_range`` (the valid box of ``w``; samples outside are
flagged), ``input_check`` (a finer validity predicate), ``effects`` (extension inputs
the diagnosis may add, ``effect_fn(w, theta, e) -> x``) and ``file_readers``.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping, Sequence
from typing import Any

import jax.numpy as jnp
import numpy as np

from jaxcal.model_contract import (
    ModelContractError,
    check_functions,
    check_warm_start,
    checked_output,
    checked_state,
    initial_state_fn,
    split_output,
    split_step,
    traced_call,
    warm_output,
)
from jaxcal.model_spec import (
    DiagnosisHints,
    ModelInfo,
    Parameter,
    StepFn,
    Variable,
    as_parameters,
    as_range,
    as_variables,
    check_vocabulary,
    names_to_index,
)
from jaxcal.typedefs import Array

__all__ = [
    "DiagnosisHints",
    "Model",
    "ModelContractError",
    "ModelInfo",
    "Parameter",
    "StepFn",
    "Variable",
    "names_to_index",
]


@dataclasses.dataclass(frozen=True, eq=False)
class Model:
    """A physics model: names, units, bounds and pure functions.

    Build one with :meth:`from_function` (static) or :meth:`from_step` (hidden
    states); ``jaxcal.models.load("cmapss")`` returns the turbofan.

    Attributes:
        name: a label for reports and run folders.
        conditions: ``W`` operating conditions ``w`` (names, units).
        parameters: ``P_all`` parameters ``theta`` (name, nominal, bounds, unit).
        outputs: ``S_all`` outputs ``x`` (names, units).
        step_fn: ``step(state [Z], w, theta) -> (state, x, valid)``; ``valid`` is a
            ``[]`` bool or a :class:`ModelInfo`.
        init_state_fn: ``init_state(w0, theta) -> state [Z]``.
        states: ``Z`` hidden-state names (empty for a static model).
        condition_range: ``(low [W], high [W])`` valid box of ``w`` (±inf allowed).
        input_check: optional finer validity predicate ``check(w) -> [] bool``.
        effects: model-specific extension inputs for the diagnosis (their nominal
            value is "no effect").
        effect_fn: ``effect_fn(w, theta, e [E]) -> x`` (or ``(x, valid)``, like
            ``fn``) when ``effects`` is set.
        diagnosis: :class:`DiagnosisHints` (scales, noise levels, outputs to leave
            out of a residual) for the diagnosis; all optional.
        x64: the model needs float64 (an iterative solver inside).
        native: the object the model wraps (e.g. the turbofan ``Engine``), or None.
        hinted_fn: optional warm-started ``fn``, ``hinted_fn(w, theta, hint) ->
            (x, valid, next_hint)``: the same x to the model's solver tolerance,
            cheaper when ``hint`` is the previous call's along a stream (a fleet
            vmaps it: ``jaxcal.models.turbofan.physics.warm_start`` on a fall-back).
        initial_hint: ``initial_hint() -> hint``, the hint before any call.
        warm_fn, warm_size: optional ``warm_fn(w, theta, e, z0) -> (x, valid, z)``:
            from the solver start ``z0`` [warm_size] (NaN: its own), its solution
            ``z`` (:mod:`jaxcal.diagnosis.kinds.linearization`).
        origin: ``"jaxcal.models:<name>"`` for a built-in model (its compiled
            programs can be kept on disk, :mod:`jaxcal.calibrators.programs.on_disk`).
        file_readers: ``{".ext": reader(path, *, nonfinite, rename, **options) ->
            Dataset}``, the model's own files for ``read_dataset`` (the turbofan's).
    """

    name: str
    conditions: tuple[Variable, ...]
    parameters: tuple[Parameter, ...]
    outputs: tuple[Variable, ...]
    step_fn: StepFn
    init_state_fn: Callable[[Array, Array], Array]
    states: tuple[Variable, ...] = ()
    condition_range: tuple[np.ndarray, np.ndarray] | None = None
    input_check: Callable[[Array], Array] | None = None
    effects: tuple[Parameter, ...] = ()
    effect_fn: Callable[[Array, Array, Array], Array] | None = None
    x64: bool = False
    native: Any = None
    diagnosis: DiagnosisHints = DiagnosisHints()
    hinted_fn: Callable[[Array, Array, Any], Any] | None = None
    initial_hint_fn: Callable[[], Any] | None = None
    warm_fn: Callable[[Array, Array, Array, Array], Any] | None = None
    warm_size: int = 0
    origin: str | None = None
    file_readers: Mapping[str, Callable] = dataclasses.field(default_factory=dict)

    # ---------------------------------------------------------------- builders

    @classmethod
    def from_function(
        cls,
        fn: Callable[[Array, Array], Any],
        *,
        conditions,
        parameters,
        outputs,
        name: str = "model",
        condition_range: tuple[Sequence[float], Sequence[float]] | None = None,
        input_check: Callable[[Array], Array] | None = None,
        effects=None,
        effect_fn: Callable[[Array, Array, Array], Array] | None = None,
        x64: bool = False,
        native: Any = None,
        diagnosis: DiagnosisHints | None = None,
        hinted_fn: Callable[[Array, Array, Any], Any] | None = None,
        initial_hint: Callable[[], Any] | None = None,
        warm_fn: Callable[[Array, Array, Array, Array], Any] | None = None,
        warm_size: int = 0,
    ) -> Model:
        """A static model from a pure JAX function ``fn(w [W], theta [P]) -> x [S]``.

        ``fn`` may also return ``(x, valid)`` with ``valid`` a ``[]`` bool or a
        :class:`ModelInfo`. ``conditions`` / ``outputs``: names, ``{name: unit}`` or
        :class:`Variable` s; ``parameters``: ``{name: (nominal, low, high[, unit])}``.
        ``hinted_fn`` / ``initial_hint``: an optional warm-started ``fn`` (both or
        neither), ``warm_fn`` / ``warm_size``: see the class attributes.
        """
        if (hinted_fn is None) != (initial_hint is None):
            raise ValueError(
                "hinted_fn and initial_hint go together: give both or none"
            )
        check_warm_start(warm_fn, warm_size)

        check_functions(
            str(name), (fn, "fn(w, theta)"),
            (hinted_fn, "hinted_fn(w, theta, hint)"), (initial_hint, "initial_hint()"),
            (warm_fn, "warm_fn(w, theta, e, z0)"),
        )  # fmt: skip
        declared = [v.name for v in as_variables(outputs, "outputs")]

        def step(state, w, theta):
            call = "fn(w, theta)"
            out = traced_call(fn, (w, theta), model=str(name), call=call)
            x, valid = split_output(out, declared, model=str(name), call=call)
            return state, x, valid

        def init_state(w0, theta):
            del w0, theta
            return jnp.zeros((0,), jnp.result_type(float))

        return cls._build(
            name, conditions, parameters, outputs, step, init_state, (),
            condition_range, input_check, effects, effect_fn, x64, native,
            diagnosis=diagnosis, hinted_fn=hinted_fn, initial_hint_fn=initial_hint,
            warm_fn=warm_fn, warm_size=int(warm_size),
        )  # fmt: skip

    @classmethod
    def from_step(
        cls,
        step: Callable[[Array, Array, Array], Any],
        *,
        init_state,
        states,
        conditions,
        parameters,
        outputs,
        name: str = "model",
        condition_range: tuple[Sequence[float], Sequence[float]] | None = None,
        input_check: Callable[[Array], Array] | None = None,
        x64: bool = False,
    ) -> Model:
        """A stateful model from ``step(state [Z], w, theta) -> (next_state, x)``.

        ``init_state`` is ``init_state(w0, theta) -> state [Z]`` or a fixed ``[Z]``
        array. Every method of :func:`jaxcal.calibrate` takes such a model: the UKF
        filters the states jointly with the parameters, least squares fits the
        window's initial state too, E2E reads a window of past samples, a policy
        trains on the model's own step (``dynamics=physics``); ``result.states``
        holds the estimated states (docs/memory.md). A state observed directly as an
        output may share its name (an output ``T_air`` that is the state ``T_air``).
        """
        check_functions(
            str(name), (step, "step(state, w, theta)"),
            (init_state if callable(init_state) else None, "init_state(w0, theta)"),
        )  # fmt: skip
        init_fn = initial_state_fn(
            init_state, [v.name for v in as_variables(states, "states")], str(name)
        )

        def step_fn(state, w, theta):
            call = "step(state, w, theta)"
            out = traced_call(step, (state, w, theta), model=str(name), call=call)
            return split_step(out, model=str(name), call=call)

        return cls._build(
            name, conditions, parameters, outputs, step_fn, init_fn,
            as_variables(states, "states"), condition_range, input_check, None, None,
            x64, None,
        )  # fmt: skip

    @classmethod
    def _build(
        cls, name, conditions, parameters, outputs, step, init_state, states,
        condition_range, input_check, effects, effect_fn, x64, native,
        diagnosis=None, hinted_fn=None, initial_hint_fn=None, warm_fn=None,
        warm_size=0,
    ) -> Model:  # fmt: skip
        conditions = as_variables(conditions, "conditions")
        condition_range = as_range(condition_range, len(conditions))
        effects = as_parameters(effects, "effects") if effects else ()
        if effects and effect_fn is None:
            raise ValueError("effects need an effect_fn(w, theta, e) -> x")
        check_functions(
            str(name), (input_check, "input_check(w)"),
            (effect_fn, "effect_fn(w, theta, e)"), required=0,
        )  # fmt: skip
        parameters = as_parameters(parameters)
        outputs = as_variables(outputs, "outputs")
        check_vocabulary(
            condition=conditions, parameter=parameters, output=outputs, state=states,
            effect=effects,
        )  # fmt: skip
        return cls(
            name=str(name),
            conditions=conditions,
            parameters=parameters,
            outputs=outputs,
            step_fn=step,
            init_state_fn=init_state,
            states=tuple(states),
            condition_range=condition_range,
            input_check=input_check,
            effects=effects,
            effect_fn=effect_fn,
            x64=bool(x64),
            native=native,
            diagnosis=DiagnosisHints() if diagnosis is None else diagnosis,
            hinted_fn=hinted_fn,
            initial_hint_fn=initial_hint_fn,
            warm_fn=warm_fn,
            warm_size=warm_size,
        )

    # ---------------------------------------------------------------- names

    @property
    def condition_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.conditions)

    @property
    def parameter_names(self) -> tuple[str, ...]:
        return tuple(p.name for p in self.parameters)

    @property
    def output_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.outputs)

    @property
    def state_names(self) -> tuple[str, ...]:
        return tuple(v.name for v in self.states)

    @property
    def is_stateful(self) -> bool:
        return bool(self.states)

    @property
    def nominal(self) -> np.ndarray:
        """``[P_all]`` nominal parameter values."""
        return np.array([p.nominal for p in self.parameters])

    @property
    def bounds(self) -> tuple[np.ndarray, np.ndarray]:
        """``(low [P_all], high [P_all])``."""
        return (
            np.array([p.low for p in self.parameters]),
            np.array([p.high for p in self.parameters]),
        )

    def parameter_index(self, names: Sequence[str]) -> list[int]:
        return names_to_index(names, self.parameter_names, f"{self.name} parameters")

    def output_index(self, names: Sequence[str]) -> list[int]:
        return names_to_index(names, self.output_names, f"{self.name} outputs")

    def unit_of(self, name: str) -> str:
        """The unit of a condition, parameter, output or state called ``name``."""
        for v in (*self.conditions, *self.outputs, *self.states, *self.parameters):
            if v.name == name:
                return v.unit
        raise ValueError(f"{self.name} has no variable {name!r}")

    # ---------------------------------------------------------------- evaluation

    def inputs_valid(self, w: Array) -> Array:
        """``[]`` bool: ``w`` is finite, inside ``condition_range`` and passes
        ``input_check``."""
        ok = jnp.all(jnp.isfinite(w))
        if self.condition_range is not None:
            low, high = self.condition_range
            ok = ok & jnp.all((w >= low) & (w <= high))
        if self.input_check is not None:
            call = "input_check(w)"
            ok = ok & traced_call(self.input_check, (w,), model=self.name, call=call)
        return ok

    def _info(self, w, theta, x, valid) -> ModelInfo:
        native = None
        if isinstance(valid, ModelInfo):
            valid, native = valid.valid, valid.native
        ok = (
            self.inputs_valid(w)
            & jnp.all(jnp.isfinite(theta))
            & jnp.all(jnp.isfinite(x))
        )
        if valid is not None:
            ok = ok & jnp.asarray(valid, bool)
        return ModelInfo(valid=ok, native=native)

    def init_state(self, w0: Array, theta: Array) -> Array:
        """``[Z]`` initial hidden state (``[0]`` for a static model)."""
        state = self.init_state_fn(w0, theta)
        return checked_state(self, state, "init_state(w0, theta)")

    def step(self, state: Array, w: Array, theta: Array):
        """``(next_state [Z], x [S_all], ModelInfo)`` of one sample (pure, jittable).

        Raises:
            ModelContractError: the model's function returned another shape or
                dtype than its declared outputs / states (checked at trace time).
        """
        next_state, x, valid = self.step_fn(state, w, theta)
        call = "step(state, w, theta)" if self.is_stateful else "fn(w, theta)"
        next_state = checked_state(self, next_state, call)
        x, valid = checked_output(self, x, valid, call)
        return next_state, x, self._info(w, theta, x, valid)

    def evaluate(self, w: Array, theta: Array) -> tuple[Array, ModelInfo]:
        """``x = F(w [W], theta [P_all]) -> (x [S_all], ModelInfo)`` (static models).

        Raises:
            ValueError: the model is stateful (use :meth:`step`).
        """
        if self.is_stateful:
            raise ValueError(
                f"model {self.name!r} has hidden states {self.state_names}: use "
                "model.step(state, w, theta)"
            )
        empty = jnp.zeros((0,), jnp.result_type(theta))
        _, x, info = self.step(empty, w, theta)
        return x, info

    @property
    def has_hint(self) -> bool:
        """True when the model has a warm-started form (:meth:`evaluate_hinted`)."""
        return self.hinted_fn is not None

    def initial_hint(self) -> Any:
        """The hint before a stream's first call (``None`` without a warm start)."""
        return None if self.initial_hint_fn is None else self.initial_hint_fn()

    def evaluate_hinted(
        self, w: Array, theta: Array, hint: Any
    ) -> tuple[Array, ModelInfo, Any]:
        """``(x [S_all], ModelInfo, next_hint)`` of one sample, warm-started.

        ``hint`` is the previous call's (:meth:`initial_hint` first). A model
        without a warm start evaluates as :meth:`evaluate` and passes the hint
        through unchanged, so a caller can always carry it.
        """
        if self.hinted_fn is None:
            x, info = self.evaluate(w, theta)
            return x, info, hint
        x, valid, next_hint = traced_call(
            self.hinted_fn, (w, theta, hint), model=self.name,
            call="hinted_fn(w, theta, hint)",
        )  # fmt: skip
        x, valid = checked_output(self, x, valid, "hinted_fn(w, theta, hint)")
        return x, self._info(w, theta, x, valid), next_hint

    def evaluate_effects(
        self, w: Array, theta: Array, e: Array
    ) -> tuple[Array, ModelInfo]:
        """``(x [S_all], ModelInfo)`` with the extension inputs ``e [E]`` applied
        (validity as in :meth:`evaluate`)."""
        if self.effect_fn is None:
            raise ValueError(f"model {self.name!r} registers no effects")
        call = "effect_fn(w, theta, e)"
        out = traced_call(self.effect_fn, (w, theta, e), model=self.name, call=call)
        x, valid = split_output(out, self.output_names, model=self.name, call=call)
        x, valid = checked_output(self, x, valid, call)
        return x, self._info(w, theta, x, valid)

    def evaluate_from(self, w: Array, theta: Array, e: Array, z0: Array):
        """``(x [S_all], ModelInfo, z [warm_size])``: :attr:`warm_fn` from ``z0``
        (validity as in :meth:`evaluate`)."""
        x, valid, z = warm_output(self, w, theta, e, z0)
        return x, self._info(w, theta, x, valid), z

    def restrict(
        self,
        theta_names: Sequence[str],
        output_names: Sequence[str] | None = None,
        theta_base: Array | None = None,
    ) -> Callable[[Array, Array], Array]:
        """``F(w, theta_declared [P]) -> x_used [S]``: the other parameters are held
        at ``theta_base`` (default the nominal values), only the used outputs kept.
        ``jax.jacfwd`` of it costs ``P`` tangent sweeps, not one per model parameter.
        """
        place, used = self._restriction(theta_names, output_names, theta_base)

        def measure(w: Array, theta: Array) -> Array:
            x, _ = self.evaluate(w, place(theta))
            return x if used is None else x[used]

        return measure

    def restrict_hinted(
        self,
        theta_names: Sequence[str],
        output_names: Sequence[str] | None = None,
        theta_base: Array | None = None,
    ) -> Callable[[Array, Array, Any], tuple[Array, Any]]:
        """:meth:`restrict` with the warm start: ``F(w, theta [P], hint) -> (x_used
        [S], next_hint)`` (see :meth:`evaluate_hinted`)."""
        place, used = self._restriction(theta_names, output_names, theta_base)

        def measure(w: Array, theta: Array, hint: Any) -> tuple[Array, Any]:
            x, _, hint = self.evaluate_hinted(w, place(theta), hint)
            return (x if used is None else x[used]), hint

        return measure

    def _restriction(self, theta_names, output_names, theta_base):
        """``(place, used)``: ``place(theta) -> full theta``, ``where(hit, theta[slot],
        base)`` (a select of a gather fuses into its consumers; a scatter is a kernel
        of its own on XLA's CPU runtime), and the used outputs (``None``: all)."""
        declared = np.asarray(self.parameter_index(theta_names))
        out_index = self.output_index
        used = None if output_names is None else np.asarray(out_index(output_names))
        base = np.asarray(self.nominal if theta_base is None else theta_base)
        if base.shape != (len(self.parameters),):
            raise ValueError(
                f"theta_base must be [{len(self.parameters)}], got {base.shape}"
            )
        hit = np.isin(np.arange(base.size), declared)
        slot = np.zeros(base.shape, np.int32)
        slot[declared] = np.arange(declared.size)

        def place(theta: Array) -> Array:
            return jnp.where(hit, theta[slot], jnp.asarray(base, theta.dtype))

        return place, used

    def __repr__(self) -> str:
        kind = f"stateful, Z={len(self.states)}" if self.states else "static"
        return (
            f"Model({self.name!r}, {kind}, W={len(self.conditions)}, "
            f"P={len(self.parameters)}, S={len(self.outputs)})"
        )
