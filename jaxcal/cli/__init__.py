"""Every command line of the package, each a thin ``main`` over the library.

``python -m jaxcal.<tool>`` runs :mod:`jaxcal.cli.<tool>`: :mod:`~jaxcal.cli.train`
(a training run), :mod:`~jaxcal.cli.evaluate` (a trained run on a data split or
file), :mod:`~jaxcal.cli.diagnose` (the residual diagnosis), :mod:`~jaxcal.cli.generate`
(a data set file), :mod:`~jaxcal.cli.bench` (engine throughput),
:mod:`~jaxcal.cli.validate` (``python -m jaxcal.validate``: the engine
against its reference) and :mod:`~jaxcal.cli.fleet` (``python -m jaxcal.fleet``:
a fleet file, sharded and streamed). The documented module paths
(``jaxcal/train.py``, ``jaxcal/fleet/__main__.py``, ...) are shims that only forward
here. :mod:`jaxcal.cli.args` is the shared front: help, usage and exit codes (0 done,
2 bad arguments); ``key=value`` tokens are parsed by
:func:`jaxcal.settings.parse_overrides`. Only this package parses arguments,
defines a ``main`` or switches float64 on for the process; nothing below imports it.
"""
