"""The NPE peer (``jaxcal.paper.npe``): a known posterior, scores, the missing extra.

The sbi tests fit a small MAF on x = theta + noise, whose posterior is known (a normal
of std 0.1 around x, cut to the prior box); the others run without sbi: features,
training pairs, interval scores on hand-made draws, and the clear message, skipped
step and report line when sbi cannot be imported.
"""

import builtins
import importlib.util
import sys
from pathlib import Path

import jax
import numpy as np
import pytest

from jaxcal.data.padded import Padded
from jaxcal.paper import npe, npe_steps
from jaxcal.problem import Normalisation

ROOT = Path(__file__).resolve().parents[2]
NOISE = 0.1
TINY = npe.NPEConfig(
    hidden_features=16, num_transforms=2, max_samples=3000, batch_size=256,
    max_epochs=25, stop_after_epochs=5, num_posterior_samples=200, deploy_batch=128,
)  # fmt: skip


def _toy(seed: int, num: int):
    """theta ~ U(0, 1); features [theta + N(0, 0.1), pure noise]."""
    rng = np.random.default_rng(seed)
    theta = rng.uniform(0.0, 1.0, (num, 1)).astype(np.float32)
    feats = np.concatenate(
        [theta + NOISE * rng.standard_normal((num, 1)), rng.standard_normal((num, 1))],
        axis=1,
    ).astype(np.float32)
    return theta, feats


@pytest.fixture(scope="module")
def toy_posterior(tmp_path_factory):
    pytest.importorskip("sbi")
    theta, feats = _toy(0, TINY.max_samples)
    cwd = tmp_path_factory.mktemp("cwd")
    with pytest.MonkeyPatch.context() as mp:
        mp.chdir(cwd)
        posterior, info = npe.fit_npe(theta, feats, [0.0], [1.0], TINY, seed=0)
    assert not (cwd / "sbi-logs").exists()  # no TensorBoard files in the cwd
    return posterior, info


def test_npe_recovers_a_known_posterior(toy_posterior):
    posterior, info = toy_posterior
    assert info["num_samples"] == TINY.max_samples
    assert 1 <= info["best_epoch"] <= info["epochs_run"] <= TINY.max_epochs
    theta, feats = _toy(1, 400)
    summary = npe.posterior_summary(posterior, feats, TINY, seed=0)
    assert summary["mean"].shape == (400, 1) and summary["seconds"] > 0
    rmse = float(np.sqrt(np.mean((summary["mean"] - theta) ** 2)))
    # the exact posterior mean scores ~0.09 (the box cuts the normal near 0 and 1);
    # ignoring x gives ~0.29
    assert 0.06 < rmse < 0.14, rmse
    scores = npe.interval_scores(summary, theta, ["theta"])
    assert 0.75 < scores["coverage90"] < 0.99, scores
    assert 0.75 < scores["coverage90_gauss"] < 0.99, scores
    assert 0.05 < scores["posterior_std_mean"] < 0.15, scores
    # draws come from the prior's box (sbi rejects the rest)
    assert (summary["q05"] >= 0).all() and (summary["q95"] <= 1).all()


def test_npe_is_reproducible_and_round_trips(toy_posterior, tmp_path):
    posterior, _ = toy_posterior
    _, feats = _toy(2, 50)
    path = npe.save_posterior(tmp_path / "post.pt", posterior, TINY)
    loaded = npe.load_posterior(path)
    a = npe.posterior_summary(posterior, feats, TINY, seed=3)
    b = npe.posterior_summary(loaded, feats, TINY, seed=3)
    np.testing.assert_array_equal(a["mean"], b["mean"])
    lat = npe.single_stream_latency(posterior, feats, TINY, repeats=3, seed=0)
    assert lat["repeats"] == 3 and 0 < lat["min_s"] <= lat["median_s"]
    with pytest.raises(FileNotFoundError, match="fit step"):
        npe.load_posterior(tmp_path / "none.pt")


def test_features_and_training_pairs_use_valid_samples_and_the_norm():
    norm = Normalisation(
        w_mean=np.array([1.0]), w_std=np.array([2.0]),
        x_mean=np.array([10.0, 0.0]), x_std=np.array([1.0, 4.0]),
    )  # fmt: skip
    units = Padded(
        w=np.arange(6.0).reshape(2, 3, 1),
        x=np.arange(12.0).reshape(2, 3, 2),
        theta=np.arange(6.0).reshape(2, 3, 1),
        lengths=np.array([3, 1], np.int32),
        unit_ids=np.array([5, 6]),
    )
    theta, feats = npe.training_pairs(jax.random.key(0), units, norm, max_samples=10)
    np.testing.assert_array_equal(theta[:, 0], [0.0, 1.0, 2.0, 3.0])  # padding out
    np.testing.assert_allclose(feats[0], [(0 - 1) / 2, (0 - 10) / 1, (1 - 0) / 4])
    assert feats.dtype == np.float32
    theta, _ = npe.training_pairs(jax.random.key(0), units, norm, max_samples=2)
    assert theta.shape == (2, 1) and len(np.unique(theta)) == 2


def test_interval_scores_count_the_truth_inside_each_interval():
    summary = {
        "mean": np.array([[0.0], [0.0]]),
        "std": np.array([[1.0], [1.0]]),
        "q05": np.array([[-1.0], [-1.0]]),
        "q95": np.array([[1.0], [1.0]]),
    }
    truth = np.array([[0.5], [1.5]])  # first inside both, second inside the Gaussian
    scores = npe.interval_scores(summary, truth, ["a"])
    assert scores["coverage90"] == 0.5 and scores["coverage90_gauss"] == 1.0
    assert scores["coverage90_per_param"] == {"a": 0.5}
    assert scores["interval90_width_mean"] == 2.0


@pytest.fixture
def no_sbi(monkeypatch):
    """Make ``import sbi`` / ``import torch`` fail, as without the extra."""
    real_import = builtins.__import__

    def fake_import(name, *args, **kwargs):
        if name.split(".")[0] in ("sbi", "torch"):
            raise ModuleNotFoundError(f"No module named {name!r}")
        return real_import(name, *args, **kwargs)

    monkeypatch.setattr(builtins, "__import__", fake_import)
    monkeypatch.setattr(npe, "is_available", lambda: False)


def test_missing_sbi_gives_the_install_hint_not_a_crash(no_sbi):
    with pytest.raises(npe.NPEUnavailable, match=r"pip install -e '\.\[npe\]'"):
        npe.require_sbi()
    # the steps report it (the suite is never touched)
    out = npe_steps.fit_step(object(), npe.NPEConfig(), seed=0)
    assert out["skipped"].startswith("sbi not installed: pip install -e '.[npe]'")
    lines = npe_steps.npe_table({})
    assert lines == [f"NPE not scored: {npe.MISSING_HINT}."]


def _load_paper():
    spec = importlib.util.spec_from_file_location(
        "paper_script_npe", ROOT / "experiments" / "paper.py"
    )
    module = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = module
    spec.loader.exec_module(module)
    return module


@pytest.mark.parametrize("available", [False, True])
def test_the_plan_has_the_npe_steps_only_with_sbi(monkeypatch, tmp_path, available):
    paper = _load_paper()
    monkeypatch.setattr(npe, "is_available", lambda: available)
    preset, _, _ = paper.parse_args(["preset=quick"])
    names = [s.name for s in paper.make_plan(paper.Context(preset, tmp_path, 0))]
    assert (set(npe_steps.STEPS) <= set(names)) is available
    assert not set(npe_steps.STEPS) & set(names) or available
    preset, _, _ = paper.parse_args(["preset=quick", "skip=NPE"])
    names = [s.name for s in paper.make_plan(paper.Context(preset, tmp_path, 0))]
    assert not set(npe_steps.STEPS) & set(names)
