"""The E2E network ``theta_t = G(w_t, x_t, x_{t-1})`` (Tian et al. §2.4, eq. e2e):
given weights, else trained on simulations of the model over the box at the data's
own conditions (E2E-sim, :mod:`jaxcal.calibrators.methods.e2e.simulated`); checked
against the data's range."""

from __future__ import annotations

import dataclasses
from typing import Any

from jaxcal.calibrators.methods.options import learned_built
from jaxcal.calibrators.methods.protocol import Method


@dataclasses.dataclass(frozen=True)
class E2E:
    """The E2E network ``theta_t = G(w_t, x_t, x_{t-1})``: given weights
    (``e2e=``), else trained on simulations of the model (E2E-sim) with
    ``e2e_config``; ``e2e_window``: past samples G reads (a model with memory:
    16); ``e2e_copies``: simulated fleets."""

    e2e: Any = dataclasses.field(default=None, compare=False)
    e2e_config: Any = None
    e2e_window: int | None = None
    e2e_copies: int = 8

    name = "e2e"


def _range_check(problem):
    # lazy: the registry imports every method package; the implementations load
    # when a method is built (the policy's: its envs and networks)
    from jaxcal.calibrators.methods.policy.calibrator import range_check

    return range_check(problem)


def build(problem, cfg: E2E, buckets, seed: int = 0):
    """The network (trained first without weights) run over the padded groups."""
    # lazy: the registry imports every method package; the simulator loads when built
    from jaxcal.calibrators.methods.e2e.simulated import e2e_calibrator

    cal = e2e_calibrator(problem, buckets, seed, cfg)
    return learned_built(problem, cal, _range_check(problem))


def make(problem, cfg: E2E, buckets=None, seed: int = 0):
    """One stream's network; E2E-sim needs the data's ``buckets`` to train on."""
    if buckets is None and cfg.e2e is None:
        raise ValueError("E2E-sim trains on the data's conditions: pass buckets=")
    return build(problem, cfg, buckets, seed).calibrator


METHOD = Method(
    name="e2e",
    config=E2E,
    build=build,
    make=make,
    check=lambda problem, cfg: _range_check(problem),
    label="E2E",
    needs_all_rows=True,  # E2E-sim trains on the whole data set's conditions
    chooses_parameters=lambda options: not options.get("e2e"),  # weights fix them
)
