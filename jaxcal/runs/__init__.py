"""Run folders: their layout, checkpoints, metrics log, atomic writes and lock.

Host-only leaves at the bottom of the package (they know files, not models):

* :mod:`jaxcal.runs.folder`: what ``runs/<name>/`` holds, resume checks, JSON files;
* :mod:`jaxcal.runs.checkpoint`: Orbax checkpoints of whole pytrees + ``config.json``;
* :mod:`jaxcal.runs.metrics_log`: the JSON-lines metrics log;
* :mod:`jaxcal.runs.atomic`: the one atomic writer (temporary file, then rename);
* :mod:`jaxcal.runs.lock`: run names confined to the runs folder, one training of a
  run at a time.

Reading a trained *policy* back needs the training job's config and components, so
that reader is :func:`jaxcal.deploy.load_run`, above the training layer. The layers
below it that take a run folder (the method table's policy, the front door:
:mod:`jaxcal.calibrators.methods.policy.trained`) call :func:`read_run` here instead, a
slot the
package root fills with that reader when ``jaxcal`` is imported (``jaxcal/__init__``,
the composition root): no module imports a layer above its own, and nothing heavy is
loaded before a run is read.
"""

from __future__ import annotations

import os
from collections.abc import Callable
from typing import Any

_READER: list[Callable[..., Any]] = []  # the one registered reader, if any


def register_run_reader(reader: Callable[..., Any]) -> None:
    """Make ``reader(run_dir, *, which, step, trust_code)`` the reader of
    :func:`read_run` (the package root registers
    :func:`jaxcal.deploy.loading.load_run`)."""
    _READER[:] = [reader]


def read_run(
    run_dir: str | os.PathLike, *, which: str = "selected", step=None, trust_code=False
):
    """A trained run's policy, read by the registered reader
    (:func:`jaxcal.deploy.loading.load_run`: its arguments and errors).

    Raises:
        RuntimeError: no reader is registered (the package root registers one, so
            only a caller that bypassed ``jaxcal/__init__`` sees this).
    """
    if not _READER:
        raise RuntimeError(
            "no run reader registered: jaxcal/__init__ registers "
            "jaxcal.deploy.loading.load_run when the package is imported"
        )
    return _READER[0](run_dir, which=which, step=step, trust_code=trust_code)
