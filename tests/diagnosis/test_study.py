"""Slow: a miniature identification study over every effect kind (make test-all)."""

import numpy as np
import pytest
from conftest import DECLARED

from jaxcal.diagnosis.data.synthetic import kinds
from jaxcal.diagnosis.pipeline import diagnose


# make test-long: every kind over three seeds; one record per family in make test:
# tests/diagnosis/test_identify.py
@pytest.mark.slow
def test_identification_rate_over_seeds_and_kinds(engine, synthetic):
    first, alarms, fallbacks = [], [], []
    for kind in kinds(engine):
        for seed in range(3):
            syn = synthetic(kind, 100 + seed)
            res = diagnose(syn.data, engine, DECLARED, noise_std=syn.noise_std)
            added = [a for a in res.added if a != "discrepancy"]
            if kind == "none":
                alarms.append(res.verdict != "none")
            elif kind == "discrepancy":
                fallbacks.append(res.discrepancy is not None)
            else:
                first.append(added == [syn.truth.name])
    assert np.mean(first) >= 0.85, first
    assert not any(alarms)
    assert np.mean(fallbacks) >= 2 / 3
