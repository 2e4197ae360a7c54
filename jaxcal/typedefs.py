"""Type aliases and the shape-letter glossary used in docstrings.

Shape letters: ``N`` seeds, ``U`` engine units, ``T`` time, ``B`` batch / parallel envs,
``S`` sensors, ``P`` calibrated parameters, ``W`` operating conditions (4), ``X`` state,
``A`` action, ``K`` sigma points. Scan outputs are time-major ``[T, B, ...]``; data sets
are ``[U, T, S]``.
"""

from __future__ import annotations

from typing import Any

import jax

Array = jax.Array
PRNGKey = jax.Array
PyTree = Any
Metrics = dict[str, jax.Array]
