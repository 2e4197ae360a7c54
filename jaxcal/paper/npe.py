"""Neural posterior estimation (NPE, ``sbi``): the amortised-inference peer.

A user who wants a posterior over theta rather than a point estimate, and who can
simulate, would reach for NPE (Papamakarios & Murray 2016; Greenberg et al. 2019,
"APT" = sbi's ``NPE_C``): a conditional density estimator q(theta | w, x) fitted by
maximum likelihood on simulated pairs, then evaluated at every measured sample — no
model call, no filter state. It is scored here on exactly E2E-sim's information: the
same simulated flights (:meth:`jaxcal.paper.suite.Suite.simulated`, the training
units' w flown with random parameter paths, x = F(w, theta)), per sample, inputs
``[w_n, x_n]`` standardised with the data set's training statistics.

Deployment: S draws from q per test sample; their mean is the estimate (theta RMSE as
for every other method), their 5 % / 95 % quantiles the central 90 % interval
(``coverage90``: the share of samples whose true theta lies inside), and mean ±
1.6449 std the Gaussian 90 % interval (``coverage90_gauss``).

``sbi`` and ``torch`` are an optional extra (``pip install -e '.[npe]'``, ``make
npe-setup``), imported inside the functions that need them; without them
:func:`require_sbi` raises :class:`NPEUnavailable` with that hint, and the steps of
:mod:`jaxcal.paper.npe_steps` report it instead of failing. Torch runs on the CPU in
float32 with ``cfg.num_threads`` threads: on a shared 2-core machine one thread is
many times faster than two fighting for the cores.
"""

from __future__ import annotations

import dataclasses
import inspect
import io
import json
import time
import warnings
from importlib.util import find_spec
from pathlib import Path

import jax
import numpy as np

from jaxcal.data.padded import Padded
from jaxcal.problem import Normalisation
from jaxcal.runs.atomic import write_atomic

MISSING_HINT = "sbi not installed: pip install -e '.[npe]' (or make npe-setup)"
GAUSS_90 = 1.6448536269514722  # the standard normal's 95 % quantile


class NPEUnavailable(ImportError):
    """``sbi`` or ``torch`` cannot be imported (the optional ``npe`` extra)."""


@dataclasses.dataclass(frozen=True)
class NPEConfig:
    """Density estimator, training budget and deployment of the NPE peer."""

    density_estimator: str = "maf"  # sbi posterior_nn model: "maf" or "nsf"
    hidden_features: int = 50  # sbi's default
    num_transforms: int = 5  # sbi's default
    # simulated (theta, w, x) pairs fitted on (a seeded subset when fewer); the
    # default takes all of E2E-sim's (SuiteConfig.e2e_max_samples = 300,000)
    max_samples: int = 300_000
    batch_size: int = 512
    learning_rate: float = 5e-4  # sbi's default
    max_epochs: int = 40  # caps the fit to a few minutes on one thread
    stop_after_epochs: int = 5  # early stopping on the validation loss
    validation_fraction: float = 0.1
    num_posterior_samples: int = 200  # S draws per test sample
    deploy_batch: int = 2048  # test samples per sample_batched call
    num_threads: int = 1  # torch intra-op threads

    def __post_init__(self):
        # sbi trains epochs 0..max_num_epochs and needs max_num_epochs >= 1
        if self.max_epochs < 2:
            raise ValueError(f"NPEConfig.max_epochs must be >= 2: {self.max_epochs}")
        if self.num_posterior_samples < 2:
            raise ValueError(
                "NPEConfig.num_posterior_samples must be >= 2 (a std and quantiles), "
                f"got {self.num_posterior_samples}"
            )


def is_available() -> bool:
    """Whether ``sbi`` and ``torch`` are installed (found, not imported: cheap)."""
    return all(find_spec(name) is not None for name in ("sbi", "torch"))


def require_sbi():
    """``(torch, sbi.inference, sbi.neural_nets, sbi.utils)``, imported lazily.

    Raises:
        NPEUnavailable: either package is missing or broken; the message says how
            to install the extra.
    """
    try:
        # optional: sbi and torch (the npe extra)
        import torch
        from sbi import inference, neural_nets, utils
    except Exception as err:  # ImportError, or a broken torch build
        raise NPEUnavailable(f"{MISSING_HINT} ({type(err).__name__}: {err})") from err
    return torch, inference, neural_nets, utils


def npe_features(w, x, norm: Normalisation) -> np.ndarray:
    """``[..., W + S]`` float32 inputs: w and x standardised by ``norm``."""
    w_n = (np.asarray(w, np.float64) - norm.w_mean) / norm.w_std
    x_n = (np.asarray(x, np.float64) - norm.x_mean) / norm.x_std
    return np.concatenate([w_n, x_n], axis=-1).astype(np.float32)


def training_pairs(
    key, units: Padded, norm: Normalisation, max_samples: int
) -> tuple[np.ndarray, np.ndarray]:
    """A seeded subset of the valid samples of ``units`` as NPE training pairs.

    Args:
        key: PRNG key of the subset.
        units: ``[U, T, ...]`` simulated units (theta are the labels).
        norm: training statistics of the data set.
        max_samples: at most this many pairs (all when fewer are valid).

    Returns:
        ``(theta [N, P], features [N, W + S])``, float32.
    """
    mask = units.mask.reshape(-1)
    rows = np.flatnonzero(mask)
    if rows.size > max_samples:
        pick = jax.random.choice(key, rows.size, (max_samples,), replace=False)
        rows = rows[np.sort(np.asarray(pick))]
    w = units.w.reshape(-1, units.w.shape[-1])[rows]
    x = units.x.reshape(-1, units.x.shape[-1])[rows]
    theta = units.theta.reshape(-1, units.theta.shape[-1])[rows]
    return theta.astype(np.float32), npe_features(w, x, norm)


class _NoTracker:
    """sbi's ``Tracker`` protocol, logging nothing: the step JSON keeps the losses."""

    log_dir = ""

    def log_metric(self, name, value, step=None):
        del name, value, step

    def log_metrics(self, metrics, step=None):
        del metrics, step

    def log_params(self, params):
        del params

    def add_figure(self, name, figure, step=None):
        del name, figure, step

    def flush(self):
        pass


def fit_npe(theta, features, low, high, cfg: NPEConfig, *, seed: int):
    """Fit q(theta | features) with sbi's NPE (APT) under a uniform prior on the box.

    Args:
        theta: ``[N, P]`` simulated parameters.
        features: ``[N, D]`` simulated inputs (:func:`npe_features`).
        low, high: ``[P]`` the parameter box (the prior; posterior draws outside it
            are rejected at deployment).
        cfg: estimator and training settings.
        seed: torch seed (initialisation, validation split, minibatches).

    Returns:
        ``(posterior, info)``: sbi's ``DirectPosterior`` and ``{"fit_seconds",
        "epochs_run", "best_epoch", "best_val_loss", "val_loss", "num_samples"}``
        (the validation loss per epoch; sbi keeps the best epoch's weights).
    """
    torch, inference, neural_nets, utils = require_sbi()
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(seed)
    theta_t = torch.as_tensor(np.asarray(theta, np.float32))
    feats_t = torch.as_tensor(np.asarray(features, np.float32))
    prior = utils.BoxUniform(
        torch.as_tensor(np.asarray(low, np.float32)),
        torch.as_tensor(np.asarray(high, np.float32)),
    )
    estimator = neural_nets.posterior_nn(
        model=cfg.density_estimator,
        hidden_features=cfg.hidden_features,
        num_transforms=cfg.num_transforms,
    )
    kwargs = {}
    if "tracker" in inspect.signature(inference.NPE).parameters:  # sbi >= 0.26
        kwargs["tracker"] = _NoTracker()  # else TensorBoard files in ./sbi-logs
    npe = inference.NPE(
        prior=prior, density_estimator=estimator, show_progress_bars=False, **kwargs
    )
    tic = time.perf_counter()
    with warnings.catch_warnings():  # sbi's notes on z-scoring and shapes
        warnings.simplefilter("ignore", UserWarning)
        npe.append_simulations(theta_t, feats_t)
        npe.train(
            training_batch_size=cfg.batch_size,
            learning_rate=cfg.learning_rate,
            validation_fraction=cfg.validation_fraction,
            stop_after_epochs=cfg.stop_after_epochs,
            max_num_epochs=cfg.max_epochs - 1,  # sbi: epochs 0..max inclusive
        )
        posterior = npe.build_posterior()
    seconds = time.perf_counter() - tic
    summary = npe.summary
    val = np.asarray(summary["validation_loss"], np.float64)
    return posterior, {
        "fit_seconds": seconds,
        "epochs_run": int(val.size),
        "best_epoch": int(np.argmin(val)) + 1 if val.size else 0,
        "best_val_loss": float(summary["best_validation_loss"][-1]),
        "val_loss": val.tolist(),
        "num_samples": int(theta_t.shape[0]),
    }


def posterior_summary(posterior, features, cfg: NPEConfig, *, seed: int) -> dict:
    """Mean, std and 5 % / 95 % quantiles of S posterior draws per input, batched.

    Args:
        posterior: a fitted sbi posterior.
        features: ``[N, D]`` inputs.
        cfg: ``num_posterior_samples`` (S), ``deploy_batch``, ``num_threads``.
        seed: torch seed of the draws.

    Returns:
        ``{"mean", "std", "q05", "q95"}`` (each ``[N, P]`` float64) and ``"seconds"``
        (wall time of all draws and their reduction).
    """
    torch, *_ = require_sbi()
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(seed)
    feats = np.asarray(features, np.float32)
    parts = {k: [] for k in ("mean", "std", "q05", "q95")}
    tic = time.perf_counter()
    for start in range(0, len(feats), cfg.deploy_batch):  # chunks bound the memory
        cond = torch.as_tensor(feats[start : start + cfg.deploy_batch])
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            draws = posterior.sample_batched(
                (cfg.num_posterior_samples,), x=cond, show_progress_bars=False
            )  # [S, B, P]
        for name, value in _reduce(torch, draws).items():
            parts[name].append(value)
    seconds = time.perf_counter() - tic
    out = {k: np.concatenate(v).astype(np.float64) for k, v in parts.items()}
    return {**out, "seconds": seconds}


def _reduce(torch, draws) -> dict:
    """Mean, std and the central 90 % interval over the draws' axis 0."""
    q = torch.quantile(draws, torch.tensor([0.05, 0.95], dtype=draws.dtype), dim=0)
    return {
        "mean": draws.mean(0).numpy(),
        "std": draws.std(0).numpy(),
        "q05": q[0].numpy(),
        "q95": q[1].numpy(),
    }


def single_stream_latency(
    posterior, features, cfg: NPEConfig, *, repeats: int, seed: int
) -> dict:
    """Seconds per sample when samples arrive one at a time (cf. ``measure_latency``).

    Each call goes numpy features -> ``posterior.sample`` (S draws, rejection to the
    box) -> mean, std and quantiles back in numpy, cycling through ``features``
    after one warm-up call.

    Returns:
        ``{"median_s", "min_s", "repeats", "num_posterior_samples"}``.
    """
    torch, *_ = require_sbi()
    torch.set_num_threads(cfg.num_threads)
    torch.manual_seed(seed)
    feats = np.asarray(features, np.float32)
    times = np.empty(repeats)
    for i in range(-1, repeats):  # the harness is the stream: one call per sample
        one = feats[(i + 1) % len(feats)][None]
        tic = time.perf_counter()
        with torch.no_grad(), warnings.catch_warnings():
            warnings.simplefilter("ignore", UserWarning)
            draws = posterior.sample(
                (cfg.num_posterior_samples,), x=torch.as_tensor(one),
                show_progress_bars=False,
            )  # fmt: skip
        _reduce(torch, draws[:, None])
        if i >= 0:
            times[i] = time.perf_counter() - tic
    return {
        "median_s": float(np.median(times)),
        "min_s": float(times.min()),
        "repeats": repeats,
        "num_posterior_samples": cfg.num_posterior_samples,
    }


def interval_scores(summary: dict, theta, names) -> dict:
    """Coverage and width of the posterior's 90 % intervals against the truth.

    Args:
        summary: :func:`posterior_summary` output (``[N, P]`` arrays).
        theta: ``[N, P]`` true parameters.
        names: the ``P`` parameter names.

    Returns:
        ``coverage90`` (quantile interval) and ``coverage90_gauss`` (mean ± 1.6449
        std), pooled and per parameter, and the mean widths of both intervals.
    """
    theta = np.asarray(theta, np.float64)
    inside = (summary["q05"] <= theta) & (theta <= summary["q95"])
    gauss = np.abs(summary["mean"] - theta) <= GAUSS_90 * summary["std"]

    def per(values):
        return dict(zip(names, values.mean(axis=0).tolist(), strict=True))

    return {
        "coverage90": float(inside.mean()),
        "coverage90_per_param": per(inside),
        "coverage90_gauss": float(gauss.mean()),
        "coverage90_gauss_per_param": per(gauss),
        "interval90_width_mean": float((summary["q95"] - summary["q05"]).mean()),
        "posterior_std_mean": float(summary["std"].mean()),
    }


POSTERIOR_FORMAT = "jaxcal.npe_posterior/1"


def save_posterior(path, posterior, cfg: NPEConfig) -> Path:
    """Store a fitted posterior atomically as data, not as a pickle: its density
    estimator's weights (``state_dict``, tensors) and, as JSON text, what rebuilds
    it (``cfg``'s estimator settings, the prior's box, the features' size), so that
    :func:`load_posterior` reads it with ``torch.load(weights_only=True)``, which
    runs no code from the file (``docs/trust.md``)."""
    torch, *_ = require_sbi()
    estimator = posterior.posterior_estimator
    box = posterior.prior.base_dist  # BoxUniform: Independent(Uniform(low, high))
    meta = {
        "format": POSTERIOR_FORMAT,
        "density_estimator": cfg.density_estimator,
        "hidden_features": cfg.hidden_features,
        "num_transforms": cfg.num_transforms,
        "low": box.low.tolist(),
        "high": box.high.tolist(),
        "num_features": int(np.prod(tuple(_condition_shape(estimator)))),
    }
    payload = {"meta": json.dumps(meta), "state_dict": dict(estimator.state_dict())}
    buf = io.BytesIO()
    torch.save(payload, buf)
    return write_atomic(path, buf.getvalue())


def _condition_shape(estimator):
    """The features' shape an sbi density estimator is conditioned on."""
    shape = getattr(estimator, "condition_shape", None)
    return estimator._condition_shape if shape is None else shape


def load_posterior(path):
    """A posterior stored by :func:`save_posterior`: read with
    ``torch.load(weights_only=True)`` (tensors and plain values only), its estimator
    rebuilt from the stored settings and its weights loaded into it.

    Raises:
        FileNotFoundError: no file at ``path``.
        ValueError: the file is not a posterior of this format (naming it).
    """
    torch, inference, neural_nets, utils = require_sbi()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"no NPE posterior at {path} (run its fit step first)")
    try:
        payload = torch.load(path, weights_only=True)
        meta = json.loads(payload["meta"])
        state = payload["state_dict"]
    except Exception as err:  # noqa: BLE001 - an old pickle, a damaged file
        raise ValueError(
            f"{path}: not an NPE posterior of format {POSTERIOR_FORMAT} ({err}); "
            "run its fit step again"
        ) from None
    if meta.get("format") != POSTERIOR_FORMAT:
        raise ValueError(
            f"{path}: format {meta.get('format')!r}, not {POSTERIOR_FORMAT}"
        )
    low = torch.as_tensor(meta["low"], dtype=torch.float32)
    high = torch.as_tensor(meta["high"], dtype=torch.float32)
    builder = neural_nets.posterior_nn(
        model=meta["density_estimator"],
        hidden_features=meta["hidden_features"],
        num_transforms=meta["num_transforms"],
    )
    # the builder needs example batches for its shapes; the z-scoring they would
    # set is part of the stored weights and is overwritten by them
    gen = torch.Generator().manual_seed(0)
    theta = low + (high - low) * torch.rand((64, low.numel()), generator=gen)
    feats = torch.randn((64, meta["num_features"]), generator=gen)
    estimator = builder(theta, feats)
    estimator.load_state_dict(state)
    estimator.eval()
    return inference.DirectPosterior(
        posterior_estimator=estimator, prior=utils.BoxUniform(low, high)
    )
