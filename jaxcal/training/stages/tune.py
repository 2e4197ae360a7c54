"""Tuning the kept actor by gradient through the deployed filter (``tune.steps``).

The policy's actor is the analytic filter step plus a learned correction
(:class:`~jaxcal.agents.networks.SquashedGaussianActor` ``prior``). The actor-critic
learns that correction from the tracking cost alone, through a critic: it rarely
moves the validation theta error below its start's. In simulation the
true theta is known and the deployed policy is one differentiable ``lax.scan``, so
the correction can also be fitted the way KalmanNet fits its gain network (Revach
et al., IEEE TSP 2022, §IV-B): by backpropagation through time of the theta error
along whole simulated units, started from the kept policy. The deployed recursion is
the very function differentiated, so what is tuned is what deploys; the actor still
reads only data (the labels enter the loss, never the observation).

Units longer than ``tune.window`` rows are cut to windows of that many rows at
random starts (the filter starting afresh there), so that a step's cost does not
grow with the units' length; the scoring runs whole units.

The units are the run's simulated training units (a share with an undeclared effect
under ``simulate.effects``); the tuned policy is kept only where it lowers the theta
error on the simulated *selection* units (never trained on), scored as
``budget.select=sim_theta`` scores chunks, with early stopping on them
(``tune.patience``), so a tuning that cannot help costs a few evaluations and
returns the policy it was given.
"""

from __future__ import annotations

import shutil
import time
from collections.abc import Callable
from pathlib import Path
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
import optax

from jaxcal.calibrators.methods.policy.calibrator import PolicyParams
from jaxcal.calibrators.methods.policy.params import with_output_states
from jaxcal.data.padded import Padded
from jaxcal.envs.bias_states import BIAS_WALKS, START_WALK
from jaxcal.runs.checkpoint import Checkpointer
from jaxcal.runs.folder import POLICY_TUNED_DIR
from jaxcal.training.config_sections import TuneConfig

# a scoring this many times the start's (or not finite) ends the tuning: such a
# tuning does not come back below its start
DIVERGED = 2.0


class TuneResult(NamedTuple):
    """What :func:`tune_policy` did.

    Attributes:
        params: the policy kept (the tuned one, or the one given where tuning did
            not lower the selection error).
        improved: whether ``params`` is a tuned policy.
        record: the ``final.json`` entry (scores before and after, steps, seconds).
    """

    params: PolicyParams
    improved: bool
    record: dict


def with_tuned(params: PolicyParams, tuned: dict) -> PolicyParams:
    """``params`` with the tuned leaves: the actor, and where the filter's output
    biases are tuned (``tune.bias``) their walk ``exp(log_bias_var)``."""
    params = params.replace(actor=tuned["actor"])
    if "log_bias_var" not in tuned:
        return params
    return with_output_states(params, jnp.exp(tuned["log_bias_var"]))


def _start_tuned(start: PolicyParams, bias: bool) -> dict:
    """The tuning's first leaves: the kept actor, and with ``bias`` the output
    biases' walk at :data:`~jaxcal.envs.bias_states.START_WALK` (a filter that
    changes nothing yet)."""
    if not bias:
        return {"actor": start.actor}
    log_var = jnp.full(start.x_std.shape, np.log(START_WALK), start.x_std.dtype)
    return {"actor": start.actor, "log_bias_var": log_var}


def _walk_trials(num_out: int):
    """``(label, outputs, walk)``: the biases' walks scored before the gradient
    steps, each ``walk`` set on ``outputs`` (an index or every one) of the best so
    far: every output at once per decade (:data:`BIAS_WALKS`), then each output
    on its own (a sensor's fault and a parameter's change differ more on some
    outputs than on others). The log walk's gradient is too faint to cross
    decades in a few hundred steps."""
    for k in (slice(None), *range(num_out)):  # host side: S + 1 sets, 3 walks each
        for walk in BIAS_WALKS:
            label = f"{walk:g}" if k == slice(None) else f"{walk:g} on output {k}"
            yield label, k, walk


def _optimizer(cfg: TuneConfig, tuned: dict):
    """Adam on the actor (its gradient clipped), and on the biases' log walk with
    its own step size (``tune.bias_lr``: the walk spans decades, the actor's
    weights move by thousandths); a non-finite gradient (a diverging unit) skips
    the step, never poisons it."""
    inner = optax.chain(optax.clip_by_global_norm(cfg.clip), optax.adam(cfg.lr))
    if len(tuned) > 1:
        labels = {key: "actor" if key == "actor" else "filter" for key in tuned}
        inner = optax.multi_transform(
            {"actor": inner, "filter": optax.adam(cfg.bias_lr)}, labels
        )
    return optax.apply_if_finite(inner, max_consecutive_errors=cfg.steps + 1)


def _theta_loss(run_arrays, low, high):
    """``(tuned, params, w, x, theta, mask) -> mean squared theta error`` in
    half-box units over the valid, unflagged rows of a batch of units."""
    half = (high - low) / 2.0

    def loss(tuned, params, w, x, theta, mask):
        out = run_arrays(with_tuned(params, tuned), w, x, mask)
        used = mask if out.valid is None else mask & out.valid
        err = jnp.where(used[..., None], (out.theta - theta) / half, 0.0)
        count = jnp.maximum(jnp.sum(used), 1) * theta.shape[-1]
        return jnp.sum(jnp.square(err)) / count

    return loss


def tune_policy(
    start: PolicyParams,
    run_arrays: Callable,
    train_units: Padded,
    select_score: Callable[[PolicyParams], float],
    cfg: TuneConfig,
    key: jax.Array,
    log: Callable[[str], None] = print,
    limits: np.ndarray | None = None,
) -> TuneResult:
    """Tunes ``start``'s actor by Adam on the theta error of ``run_arrays(params, w,
    x, mask) -> CalOutput`` over batches of ``train_units`` (labelled), evaluating
    ``select_score(params) -> (score, clean scores)`` every ``cfg.eval_every``
    steps: a tuned policy is kept where it lowers the score (the selection units,
    a share with effects) without raising any clean score (clean units: the
    selection units' effect-free twins, units drawn across the box) above
    ``limits`` (default ``1 + cfg.clean_tolerance``) times the start's.

    Raises:
        ValueError: ``train_units`` carry no true theta.
    """
    if train_units.theta is None:
        raise ValueError("tune: the training units carry no true theta to tune on")
    tic = time.perf_counter()
    dtype = start.x_mean.dtype
    w = jnp.asarray(train_units.w, dtype)
    x = jnp.asarray(train_units.x, dtype)
    theta = jnp.asarray(train_units.theta, dtype)
    mask = jnp.asarray(train_units.mask)
    low, high = start.theta_low, start.theta_high
    loss = _theta_loss(run_arrays, low, high)
    bias = cfg.bias and getattr(start, "gn_filter", False)
    first = _start_tuned(start, bias)
    opt = _optimizer(cfg, first)
    num_units, num_rows = w.shape[0], w.shape[1]
    batch = min(cfg.batch_units, num_units)
    window = min(cfg.window, num_rows)
    lengths = jnp.asarray(train_units.lengths)

    def draw(key):
        """A batch of units, or of windows of ``window`` rows in them: the
        gradient through a recursion of 17,000 rows (a battery cell) cost minutes
        a step, and its size grows with the length."""
        if window == num_rows:  # whole units, as short units always are
            idx = jax.random.choice(key, num_units, (batch,), replace=False)
            return w[idx], x[idx], theta[idx], mask[idx]
        key_units, key_start = jax.random.split(key)
        idx = jax.random.choice(key_units, num_units, (batch,), replace=False)
        span = jnp.maximum(lengths[idx] - window, 0) + 1
        start = jax.random.randint(key_start, (batch,), 0, span)

        def cut(a):  # [batch, T, ...] -> [batch, window, ...] from each start
            return jax.vmap(
                lambda u, s: jax.lax.dynamic_slice_in_dim(u, s, window, axis=0)
            )(a[idx], start)

        return cut(w), cut(x), cut(theta), cut(mask)

    @jax.jit
    def update(tuned, opt_state, params, key):
        value, grad = jax.value_and_grad(loss)(tuned, params, *draw(key))
        updates, opt_state = opt.update(grad, opt_state, tuned)
        return optax.apply_updates(tuned, updates), opt_state, value

    before, clean_before = select_score(start)
    clean_before = np.asarray(clean_before, float)
    # a tuned policy may not lose on clean units what it gains under effects
    factor = 1.0 + cfg.clean_tolerance if limits is None else np.asarray(limits)
    clean_limit = clean_before * factor
    best_score, best, tuned = before, start, first
    best_clean = clean_before
    trials = _walk_trials(start.x_std.shape[-1]) if bias else ()
    for label, outputs, walk in trials:  # then Adam
        value = tuned["log_bias_var"].at[outputs].set(np.log(walk))
        trial = {**tuned, "log_bias_var": value}
        score, clean = select_score(with_tuned(start, trial))
        over = np.flatnonzero(clean > clean_limit)
        refused = f" (refused: guard set {over.tolist()} above its limit)"
        log(f"tune: output-bias walk {label}: selection score {score:.4e}"
            + (refused if over.size else ""))  # fmt: skip
        if np.isfinite(score) and score < best_score and not over.size:
            best, best_score, best_clean = with_tuned(start, trial), score, clean
            tuned = trial
    opt_state, waited, steps = opt.init(tuned), 0, 0
    for step in range(1, cfg.steps + 1):
        key, sub = jax.random.split(key)
        tuned, opt_state, value = update(tuned, opt_state, start, sub)
        steps = step
        if step % cfg.eval_every and step != cfg.steps:
            continue
        candidate = with_tuned(start, tuned)
        score, clean = select_score(candidate)
        if np.isfinite(score) and score < best_score and np.all(clean <= clean_limit):
            best, best_score, best_clean, waited = candidate, score, clean, 0
        else:
            waited += 1
        log(
            f"tune step {step}/{cfg.steps}: train theta loss {float(value):.3e}, "
            f"selection theta rmse {score:.4e} (best {best_score:.4e}; clean units "
            f"x start {np.round(clean / np.maximum(clean_before, 1e-30), 3).tolist()})"
        )
        if waited >= cfg.patience:
            break
        if not np.isfinite(score) or 0 < before * DIVERGED <= score:  # (battery)
            log(f"tune: stopped, the tuned policy scores {score / before:.1f}x start")
            break
    improved = best_score < before
    record = {
        "steps": steps,
        "selection_theta_rmse_before": before,
        "selection_theta_rmse_after": best_score,
        "clean_theta_rmse_before": np.asarray(clean_before).tolist(),
        "clean_theta_rmse_after": np.asarray(best_clean).tolist(),
        "ratio": best_score / before if before > 0 else None,
        "improved": improved,
        "seconds": time.perf_counter() - tic,
    }
    if getattr(best, "filter_bias_var", None) is not None:
        record["bias_var"] = np.asarray(best.filter_bias_var).tolist()
    log(
        f"tuned by gradient through the filter: selection theta rmse {before:.4e} "
        f"-> {best_score:.4e} ({record['ratio']:.3f}x) in {steps} steps, "
        f"{record['seconds']:.0f} s"
        if improved
        else "tuning by gradient through the filter did not lower the selection "
        f"theta rmse ({before:.4e}) in {steps} steps: the run keeps its policy"
    )
    return TuneResult(best, improved, record)


def tune_kept(cfg, kept, parts, sims, scoring, run_dir: Path, log) -> tuple:
    """``(kept, record)``: the run's kept policy tuned (:func:`tune_policy`) on
    simulated tuning units and kept where the selection and guard units agree, saved
    under ``policy_tuned/`` (the run's deployed policy; a stale one of an earlier
    session is removed first); ``record`` is ``final.json``'s ``tune`` entry
    (``None`` with ``tune.steps=0``)."""
    tuned_dir = run_dir / POLICY_TUNED_DIR
    if tuned_dir.exists():
        shutil.rmtree(tuned_dir)  # an earlier session's: this session decides anew
    if cfg.tune.steps == 0:
        return kept, None
    select_units = sims.selection_units()
    guards = sims.guard_units()  # clean twins, across the box, with effects
    train_units = sims.tuning_units(cfg.tune.effects or None)

    def scores(params) -> tuple[float, np.ndarray]:
        score = float(scoring.sim_theta(select_units, params)[0])
        clean = [float(scoring.sim_theta(u, params)[0]) for u in guards]
        return score, np.asarray(clean)

    start = kept.selected
    at_start = scores(start)
    limits = None
    if cfg.tune.effects:  # effects count as much as the clean units; clean may not lose
        limits = np.full(len(guards), 1.0 + cfg.tune.clean_tolerance)
        limits[0] = cfg.tune.clean_limit

    def select_score(params) -> tuple[float, np.ndarray]:
        score, clean = at_start if params is start else scores(params)
        if cfg.tune.effects:  # the two ratios weighed, in selection units
            (score0, clean0), eff = at_start, len(guards) - 1
            weight = cfg.tune.effects_weight
            score = score0 * (
                (1.0 - weight) * score / score0 + weight * clean[eff] / clean0[eff]
            )
        return score, clean

    key = jax.random.fold_in(jax.random.key(cfg.seed), 41)
    result = tune_policy(
        start, parts.run_units, train_units, select_score, cfg.tune, key, log, limits
    )
    if cfg.tune.effects:  # the record's selection rmse stays the selection's own
        record = result.record
        record["score_before"] = record["selection_theta_rmse_before"]
        record["score_after"] = record["selection_theta_rmse_after"]
        record["score"] = (
            f"the clean selection units' and (weight {cfg.tune.effects_weight:g}) "
            "the effects guard units' theta rmse, each x the start's, weighed, times "
            "the start's selection rmse"
        )
        record["selection_theta_rmse_before"] = at_start[0]
        record["selection_theta_rmse_after"] = (
            scores(result.params)[0] if result.improved else at_start[0]
        )
    if result.improved:
        with Checkpointer(tuned_dir, max_to_keep=1) as ckpt:
            ckpt.save(kept.selected_step, result.params, wait=True)
        # the validation run kept for the band was the untuned policy's
        kept = kept._replace(selected=result.params, val_out=None)
    return kept, result.record
