"""What a calibration method is: one :class:`Method` object its package exports.

The front door (:func:`jaxcal.calibrate`), the fleet command line and the paper's
comparison read everything they need to know about a method from this object, and
never test a method's name or config type: adding a method is one package
``jaxcal/calibrators/methods/<name>/`` exporting ``METHOD`` and one entry in the
registry (:data:`jaxcal.calibrators.methods.PACKAGES`).

A method's config is a frozen, hashable dataclass of its keyword options (it keys the
compiled programs, :mod:`jaxcal.calibrators.programs.compiled`); the options' forms are
checked by :mod:`jaxcal.calibrators.methods.options`. The functions below are what
the callers ask of a method; the defaults suit a method on the model that reads the
measurement noise.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from typing import Any


def _unchanged(options: dict, theta, outputs):
    return options, theta, outputs


def _all_options(options: dict) -> bool:
    del options
    return True


def default_screening(cfg):
    """A default UKF's settings with the method's hidden-state settings
    (``state_std``, ``state_q``) where it has them."""
    # cycle: the ukf package (its Method) imports this module
    from jaxcal.calibrators.methods.ukf import UKF  # the registry's own UKF

    return UKF(
        state_std=getattr(cfg, "state_std", None), state_q=getattr(cfg, "state_q", None)
    )


@dataclasses.dataclass(frozen=True)
class Method:
    """One calibration method.

    Attributes:
        name: its name in ``jaxcal.calibrate(method=...)`` and ``method=`` of the
            command lines.
        config: the frozen dataclass of its options (:func:`options.config_of`).
        build: ``build(problem, cfg, buckets, seed) -> Built``: its fleet program
            over padded unit groups and the std known before a first sample.
        make: ``make(problem, cfg, buckets, seed) -> Calibrator``: one stream's
            calibrator (``buckets`` may be ``None`` where the method does not learn
            from the data).
        check: ``check(problem, cfg) -> SampleCheck | None``: the input box a
            stream's samples are checked against.
        screening: ``screening(cfg) -> UKF config``: the settings of the UKF passes
            that estimate the noise and flag outliers before the method runs
            (default: a UKF with the method's hidden-state settings).
        factory: a method on the model: ``factory(problem, cfg, measure=None) ->
            make(inputs) -> Calibrator`` pure in its compiled inputs
            (:class:`~jaxcal.calibrators.programs.compiled.Inputs`), ``measure`` a
            static model's ``F`` put in place of the problem's (the paper's perturbed
            model); ``None`` for a method without a model.
        label: its name in the paper's tables.
        reads_noise: it weighs the outputs by the measurement noise (a trained
            policy does not: without a given noise nothing is screened).
        needs_run: it reads a training run (``run=<folder>``); ``prepare`` loads it.
        needs_all_rows: it learns from the whole data set before its first
            estimate (a streamed file cannot feed it).
        white_std: its std assumes white noise; under coloured innovations it is
            widened by the colour's long-run variance
            (:func:`~jaxcal.calibrators.uncertainty.misfit_check.widening`).
        chooses_parameters: ``chooses_parameters(options) -> bool``: a call chooses
            the calibrated set (a unit carrying some parameters only is then
            calibrated on its own set, :mod:`jaxcal.calibrators.front.carriers`); given
            weights or a trained run fix it.
        prepare: ``prepare(options, theta, outputs) -> (options, theta, outputs)``
            before the config is read: a run loaded, its names the defaults.
    """

    name: str
    config: type
    build: Callable
    make: Callable
    check: Callable
    screening: Callable = default_screening
    factory: Callable | None = None
    label: str = ""
    reads_noise: bool = True
    needs_run: bool = False
    needs_all_rows: bool = False
    white_std: bool = True
    chooses_parameters: Callable[[dict], bool] = _all_options
    prepare: Callable[[dict, Any, Any], tuple] = _unchanged

    @property
    def on_model(self) -> bool:
        """The method evaluates the model (it has a :attr:`factory`)."""
        return self.factory is not None
