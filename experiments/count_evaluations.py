"""The fleet evaluations and fits of a diagnosis, stage by stage.

Runs ``experiments/profile_diagnosis.py`` with the same arguments, and counts each
call of :func:`jaxcal.diagnosis.kinds.linearization.linearize` (one evaluation of the
model over the fleet's rows, with the derivatives asked for) and of
:func:`jaxcal.diagnosis.fitting.joint.fit_model` under the stage that made it (the
diagnosis's own :class:`~jaxcal.diagnosis.timing.StageClock` names). Prints the
profile's JSON on stdout, then one JSON object on stderr::

    {"evaluations": {stage: {"calls": n, "seconds": s}}, "fits": {stage: n}}

Usage::

    python experiments/count_evaluations.py data=FD002 units=260 profile=false

``results/loop/profile.md`` (round 6) reads it.
"""

from __future__ import annotations

import collections
import contextlib
import json
import os
import runpy
import sys
import time

import jaxcal.diagnosis.fitting.joint as fitting
import jaxcal.diagnosis.kinds.linearization as linearization
import jaxcal.diagnosis.pipeline  # noqa: F401 (every diagnosis module, before the patch)
import jaxcal.diagnosis.timing as timing

_stage = ["-"]
_evaluations = collections.defaultdict(lambda: [0, 0.0])
_fits = collections.Counter()


def _patch() -> None:
    enter = timing.StageClock.stage

    @contextlib.contextmanager
    def stage(self, name):
        outer, _stage[0] = _stage[0], name
        with enter(self, name):
            yield
        _stage[0] = outer

    timing.StageClock.stage = stage
    linearize = linearization.linearize

    def counted(*args, **kwargs):
        begin = time.perf_counter()
        out = linearize(*args, **kwargs)
        seen = _evaluations[_stage[0]]
        seen[0] += 1
        seen[1] += time.perf_counter() - begin
        return out

    linearization.linearize = counted
    fit = fitting.fit_model

    def fit_counted(*args, **kwargs):
        _fits[_stage[0]] += 1
        return fit(*args, **kwargs)

    for module in list(sys.modules.values()):  # every `from ... import fit_model`
        if getattr(module, "fit_model", None) is fit:
            module.fit_model = fit_counted


def main(argv: list[str]) -> int:
    _patch()
    here = os.path.dirname(os.path.abspath(__file__))
    sys.argv = ["profile_diagnosis.py", *argv]
    with contextlib.suppress(SystemExit):
        runpy.run_path(os.path.join(here, "profile_diagnosis.py"), run_name="__main__")
    counts = {
        stage: {"calls": n, "seconds": round(s, 1)}
        for stage, (n, s) in _evaluations.items()
    }
    print(json.dumps({"evaluations": counts, "fits": dict(_fits)}), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))
