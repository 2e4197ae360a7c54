"""The learned methods' fleet runner: a ``Calibrator`` built outside the compiled
programs (an E2E network, :mod:`jaxcal.calibrators.methods.e2e`; a trained policy,
:mod:`jaxcal.calibrators.methods.policy`), run by one jitted fleet scan
with the method's sample check.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from jaxcal.calibrators.interface import Calibrator, run_fleet
from jaxcal.calibrators.methods.options import Built
from jaxcal.data.padded import Padded
from jaxcal.problem import Problem

_FLEET = jax.jit(run_fleet, static_argnums=0)  # one dispatch cache per process


def learned_built(problem: Problem, cal: Calibrator, check) -> Built:
    """:class:`Built` of a learned calibrator: the jitted fleet scan with ``check``
    (the same calibrator object again runs without tracing again), and a uniform's
    std over the box before a stream's first sample."""

    def run(padded: Padded, skip=None):
        mask = padded.mask if skip is None else padded.mask & ~np.asarray(skip)
        return _FLEET(
            cal, jnp.asarray(padded.w), jnp.asarray(padded.x),
            jnp.asarray(mask), check=check,
        )  # fmt: skip

    uniform = problem.theta_half_width / np.sqrt(3.0)
    return Built(run, uniform, cal)
