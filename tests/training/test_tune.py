"""``tune``: the kept actor tuned by gradient through the deployed recursion on
labelled units, kept only where the selection score agrees (issue 41)."""

import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from jaxcal.calibrators.interface import CalOutput
from jaxcal.data.padded import Padded
from jaxcal.training.config import resolve_config
from jaxcal.training.config_sections import TuneConfig
from jaxcal.training.scoring.final_report import with_tuning
from jaxcal.training.stages.tune import tune_policy


@struct.dataclass
class _Params:
    """The fields tune_policy reads of a policy's params."""

    actor: dict
    x_mean: jnp.ndarray
    theta_low: jnp.ndarray
    theta_high: jnp.ndarray


def _units(num=6, steps=20, seed=0):
    """Units whose true theta is 0.5 x (one output, one parameter)."""
    rng = np.random.default_rng(seed)
    x = rng.uniform(-1.0, 1.0, (num, steps, 1)).astype(np.float32)
    lengths = np.full(num, steps, np.int32)
    lengths[0] = steps // 2  # padding must not enter the loss
    return Padded(x, x, 0.5 * x, lengths, np.arange(num))


def _run(params, w, x, mask):
    """A "recursion" whose theta is gain * x: the best gain is 0.5."""
    theta = params.actor["gain"] * x
    return CalOutput(theta=theta, xhat=x, valid=jnp.ones(mask.shape, bool))


def _start(gain=2.0):
    return _Params({"gain": jnp.float32(gain)}, jnp.zeros(1), -jnp.ones(1), jnp.ones(1))


def test_tuning_lowers_the_theta_error_and_keeps_the_best_scored_policy():
    cfg = TuneConfig(steps=200, lr=0.05, batch_units=3, eval_every=20, patience=3)
    said = []
    out = tune_policy(
        _start(), _run, _units(), lambda p: (abs(p.actor["gain"] - 0.5),) * 2, cfg,
        __import__("jax").random.key(0), said.append,
    )  # fmt: skip
    assert out.improved and abs(float(out.params.actor["gain"]) - 0.5) < 0.1
    assert out.record["selection_theta_rmse_after"] < 0.1
    assert out.record["selection_theta_rmse_before"] == pytest.approx(1.5)
    assert any("tuned by gradient through the filter" in s for s in said)


def test_long_units_are_tuned_on_windows_of_them():
    """``tune.window``: a step sees ``window`` rows of each unit drawn (its cost
    no longer grows with the units' length) and still learns the gain."""
    cfg = TuneConfig(steps=200, lr=0.05, batch_units=3, eval_every=20, window=5)
    seen = []

    def run(params, w, x, mask):
        seen.append(x.shape[1])  # at trace time: the rows a step differentiates
        return _run(params, w, x, mask)

    out = tune_policy(
        _start(), run, _units(), lambda p: (abs(p.actor["gain"] - 0.5),) * 2, cfg,
        __import__("jax").random.key(0),
    )  # fmt: skip
    assert seen == [5]
    assert out.improved and abs(float(out.params.actor["gain"]) - 0.5) < 0.1


def test_a_tuning_the_selection_disagrees_with_returns_the_start_early():
    """Selection prefers the start (gain 2): every tuned policy scores worse, so
    the start comes back after ``patience`` scorings, and the log says so."""
    cfg = TuneConfig(steps=400, lr=0.05, batch_units=3, eval_every=10, patience=2)
    said = []
    start = _start()
    out = tune_policy(
        start, _run, _units(), lambda p: (abs(p.actor["gain"] - 2.0),) * 2, cfg,
        __import__("jax").random.key(0), said.append,
    )  # fmt: skip
    assert not out.improved and out.params is start
    assert out.record["steps"] == 20  # two scorings, then stop
    assert any("did not lower" in s for s in said)


def test_a_diverging_tuning_stops_at_its_first_scoring():
    """A scoring twice the start's or worse ends the tuning (patience would wait
    for two more): the start is kept and the log says why."""
    cfg = TuneConfig(steps=400, lr=0.5, batch_units=3, eval_every=10, patience=3)
    said = []
    start = _start(0.55)  # near the best gain; a step size of 0.5 overshoots
    out = tune_policy(
        start, _run, _units(), lambda p: (abs(p.actor["gain"] - 0.5) + 0.01,) * 2,
        cfg,
        __import__("jax").random.key(0), said.append,
    )  # fmt: skip
    assert not out.improved and out.record["steps"] == 10
    assert any("tune: stopped" in s for s in said)


def test_units_without_labels_are_refused():
    units = _units()._replace(theta=None)
    with pytest.raises(ValueError, match="no true theta"):
        tune_policy(_start(), _run, units, lambda p: (1.0, 1.0), TuneConfig(steps=1),
                    __import__("jax").random.key(0))  # fmt: skip


def test_the_gain_record_counts_the_tuned_policy_on_the_same_score():
    gain = {"key": "val_sim_theta_rmse", "start": 2.0, "kept": 2.0, "ratio": 1.0,
            "kept_start": True, "best_trained": None}  # fmt: skip
    tuned = {"improved": True, "selection_theta_rmse_after": 1.5}
    out = with_tuning(gain, tuned)
    assert out["tuned"] and not out["kept_start"] and out["ratio"] == 0.75
    assert with_tuning(gain, {**tuned, "improved": False}) == gain
    other = {**gain, "key": "val_tracking_rmse_norm"}
    assert with_tuning(other, tuned) == other  # not the score tune selects by


def test_a_tuned_policy_that_loses_on_clean_units_is_not_kept():
    """Under effects the score improves towards gain 0.5, but the clean units
    prefer the start (gain 2): past the clean tolerance nothing is kept."""
    cfg = TuneConfig(steps=60, lr=0.05, batch_units=3, eval_every=10, patience=3)

    def score(p):
        gain = float(p.actor["gain"])
        return abs(gain - 0.5), abs(gain - 2.0)

    out = tune_policy(
        _start(), _run, _units(), score, cfg, __import__("jax").random.key(0)
    )
    assert not out.improved and out.record["clean_theta_rmse_after"] == 0.0


@pytest.mark.parametrize(
    "bad",
    [
        "tune.steps=-1",
        "tune.lr=0",
        "tune.patience=0",
        "tune.window=0",
        "tune.effects_weight=1.5",
    ],
)
def test_tune_settings_are_validated(bad):
    with pytest.raises(ValueError, match="tune."):
        resolve_config(["dataset=tiny", bad])


@struct.dataclass
class _FilterParams(_Params):
    """A filter's params: the output biases' walk is tuned beside the actor."""

    x_std: jnp.ndarray = None
    filter_bias_var: jnp.ndarray | None = None
    gn_filter: bool = struct.field(pytree_node=False, default=True)


def test_bias_walk_is_tuned_beside_the_actor_from_a_walk_that_changes_nothing():
    """``tune.bias``: the filter's output-bias walk starts at START_WALK and is
    scored per decade (BIAS_WALKS), then fitted by gradient (here the best theta
    needs a walk of 3e-3: ``theta = g x + v``, between two decades)."""
    from jaxcal.envs.bias_states import START_WALK

    units = _units()
    units = units._replace(theta=units.theta + 3e-3)

    def run(params, w, x, mask):
        out = _run(params, w, x, mask)
        walk = 0.0 if params.filter_bias_var is None else params.filter_bias_var[0]
        return out._replace(theta=out.theta + walk)

    start = _FilterParams(
        {"gain": jnp.float32(0.5)}, jnp.zeros(1), -jnp.ones(1), jnp.ones(1),
        x_std=jnp.ones(1),
    )  # fmt: skip

    def score(p):
        walk = 0.0 if p.filter_bias_var is None else float(p.filter_bias_var[0])
        return (abs(walk - 3e-3),) * 2

    cfg = TuneConfig(steps=300, lr=1e-3, bias=True, bias_lr=0.1, eval_every=20,
                     batch_units=3)  # fmt: skip
    out = tune_policy(start, run, units, score, cfg, __import__("jax").random.key(0))
    assert out.improved and out.record["bias_var"][0] == pytest.approx(3e-3, rel=0.2)
    off = tune_policy(start, run, units, score, TuneConfig(steps=20, eval_every=10),
                      __import__("jax").random.key(0))  # fmt: skip
    assert off.params is start or off.params.filter_bias_var is None
    assert START_WALK < 1e-5  # the start changes no scored theta
