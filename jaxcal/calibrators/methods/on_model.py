"""A method on the model, made from its filter makers: the UKF, the EKF, least squares.

Such a method evaluates the problem's model inside its ``Calibrator(init, step)``
(:mod:`jaxcal.calibrators.model_based`): its calibrator is pure in the compiled
inputs (noise, prior, scales), its fleet program compiled once per process
(:mod:`jaxcal.calibrators.programs.compiled`), its sample check the model's valid
input box. :func:`on_model_method` builds its :class:`~.protocol.Method` from the
two makers of its filter (a static model's and a model with memory's) and its prior
std; the rest is shared.
"""

from __future__ import annotations

from collections.abc import Callable

from jaxcal.calibrators.methods.protocol import Method
from jaxcal.calibrators.model_based import (
    fleet_built,
    model_based_factory,
    model_check,
    stream_calibrator,
)
from jaxcal.calibrators.programs import compiled


def on_model_method(
    name: str,
    config: type,
    static: Callable,
    stateful: Callable,
    *,
    label: str,
    prior_std: Callable,
    program: Callable = compiled.fleet_program,
    **traits,
) -> Method:
    """The :class:`~.protocol.Method` of a method on the model.

    Args:
        name, config, label: as :class:`~.protocol.Method`'s; ``config`` holds the
            filter's settings in its ``field_name`` field.
        static, stateful: the filter's makers (``make_ukf``, ``make_joint_ukf``; see
            :func:`~jaxcal.calibrators.model_based.model_based_factory`).
        prior_std: ``prior_std(problem, cfg) -> [P]``, what is known of theta before
            a stream's first sample.
        program: ``program(problem, cfg, make, check, dtype) -> run(inputs, w, x,
            mask)``, its compiled fleet program (default
            :func:`~jaxcal.calibrators.programs.compiled.fleet_program`).
        traits: further fields of :class:`~.protocol.Method` (``screening``,
            ``white_std``, ...).
    """
    field = config.field_name

    def factory(problem, cfg, measure=None):
        """``make(inputs) -> Calibrator``: the filter on ``problem``'s model."""
        settings = getattr(cfg, field)
        return model_based_factory(problem, settings, static, stateful, measure)

    def build(problem, cfg, buckets, seed: int = 0):
        del seed

        def program_of():
            make, check = factory(problem, cfg), model_check(problem)
            return program(problem, cfg, make, check, buckets.dtype)

        prior = prior_std(problem, cfg)
        return fleet_built(problem, cfg, program_of, prior, buckets.dtype)

    def make(problem, cfg, buckets=None, seed: int = 0):
        del buckets, seed
        return stream_calibrator(problem, cfg, factory)

    def check(problem, cfg):
        del cfg
        return model_check(problem)

    return Method(
        name=name, config=config, build=build, make=make, check=check,
        factory=factory, label=label, **traits,
    )  # fmt: skip
