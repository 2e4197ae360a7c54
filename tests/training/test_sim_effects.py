"""Undeclared effects in simulated training units (issue 41 item 3)."""

import jax
import numpy as np
import pytest

from jaxcal.training.data.sim_effects import KINDS, add_effects

U, T, S = 400, 120, 3
SD = np.array([0.1, 0.2, 0.3])


def _units(seed=0):
    rng = np.random.default_rng(seed)
    clean = 5.0 + np.sin(np.arange(T) / 10.0)[None, :, None] * np.ones((U, T, S))
    lengths = rng.integers(60, T + 1, U)
    valid = np.arange(T)[None] < lengths[:, None]
    noisy = np.where(valid[..., None], clean + SD * rng.standard_normal((U, T, S)), 0)
    return noisy, clean, lengths, valid


def test_a_share_of_units_carry_one_effect_each_within_their_rows():
    noisy, clean, lengths, valid = _units()
    out, kinds = add_effects(np.random.default_rng(1), noisy, clean, lengths, SD, 0.5)
    kinds = np.array(kinds)
    assert set(kinds) == {"none", *KINDS}
    assert 0.4 < np.mean(kinds != "none") < 0.6
    np.testing.assert_array_equal(out[kinds == "none"], noisy[kinds == "none"])
    np.testing.assert_array_equal(out[~valid], noisy[~valid])  # padding untouched
    for kind in ("bias", "step", "drift", "gain"):  # one output moved, by 1-4 stds
        units = np.flatnonzero(kinds == kind)
        moved = np.abs(out[units] - noisy[units]).max(axis=1)  # [u, S]
        assert np.all((moved > 0).sum(axis=1) == 1)
        # in stds of the output moved (a gain's peak: the level's 6 / its mean 5)
        assert np.all((moved / SD).max(axis=1) <= 4.0 * 1.25)
        assert np.all((moved / SD).max(axis=1) >= 1.0 * 0.8)
    ar = np.flatnonzero(kinds == "ar1")  # the noise coloured, its std kept
    e = (out[ar] - clean[ar]) / SD
    e = np.concatenate([e[i, : lengths[u]] for i, u in enumerate(ar)])
    assert np.std(e) == pytest.approx(1.0, abs=0.1)
    assert np.corrcoef(e[1:, 0], e[:-1, 0])[0, 1] > 0.4


def test_no_share_changes_nothing_and_a_bad_share_is_refused():
    noisy, clean, lengths, _ = _units()
    out, kinds = add_effects(np.random.default_rng(1), noisy, clean, lengths, SD, 0.0)
    np.testing.assert_array_equal(out, noisy)
    assert set(kinds) == {"none"}
    with pytest.raises(ValueError, match="simulate.effects"):
        add_effects(np.random.default_rng(1), noisy, clean, lengths, SD, 1.5)


@pytest.mark.parametrize("share", [0.0, 0.5])
def test_the_selection_units_carry_the_training_share_of_effects(monkeypatch, share):
    """With simulate.effects the policy is selected on units with the same share of
    effects (kept for holding under model error too); the band's units stay clean."""
    import types

    import jaxcal.training.data.simulated as simulated
    from jaxcal.training.config import resolve_config

    seen = []
    monkeypatch.setattr(
        simulated, "simulate_units",
        lambda *a, **k: seen.append(k.get("effects", 0.0)) or (a[1], None),
    )  # fmt: skip
    cfg = resolve_config(["dataset=tiny", f"simulate.effects={share}"])
    sims = simulated.Simulations.__new__(simulated.Simulations)
    sims.cfg, sims.key, sims.used = cfg.simulate, jax.random.key(0), {}
    sims._selection = None
    sims.data = types.SimpleNamespace(val=None, train="units")
    sims.problem = lambda: None
    sims.selection_units()
    sims.band_units()
    assert seen == [share, 0.0]
    assert ("undeclared effect" in sims.used["selection"]) == bool(share)
