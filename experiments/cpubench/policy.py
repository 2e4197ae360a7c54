"""Policy inference: the paper's actor, deterministic action, against numpy and the
matmul roofline.

The network is the squashed Gaussian actor of :mod:`jaxcal.agents.networks` at the
paper's sizes (2 x 256 leaky-ReLU, slope 0.2, Xavier weights) with the tracking MDP's
observation of the ``cmapss`` runs (14 sensors, 4 conditions: O = 2 * 14 + 4 = 32) and
action size 1; the deployed action is pi*(s) = tanh(mean). Measured in one process:

* single-sample latency: one host observation in, one blocking jitted call, the action
  back on the host; beside it the same with the observation already on the device,
  and host to host with asynchronous CPU dispatch off (a child process, see
  :func:`sync_dispatch_latency`); peer: the forward pass in numpy, same weights;
* batched throughput at ``batch`` samples per call, same peer;
* the achieved GFLOP/s of the batched policy against the roofline, a large float32
  matmul jitted by the same XLA in the same run, both at their fastest repeat
  (numpy's matmul with one OpenBLAS thread is reported beside it).

FLOPs per sample count the multiply-adds the deterministic action needs:
2 (O H1 + H1 H2 + H2 A); the log-std head is dead code there (XLA removes it, the
numpy pass skips it).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np

from cpubench.measure import (
    blocking,
    figure,
    missing_peer,
    peer,
    skipped,
    time_interleaved,
)
from jaxcal.agents.configs import CLACConfig
from jaxcal.agents.networks import deterministic_action, make_networks

SENSORS, CONDITIONS, ACTIONS = 14, 4, 1
OBS_SIZE = 2 * SENSORS + CONDITIONS


def numpy_policy(weights: list[tuple[np.ndarray, np.ndarray]], slope: float):
    """The deterministic actor in numpy: leaky-ReLU torso, mean head, tanh.

    Args:
        weights: ``[(kernel, bias)]`` of the hidden layers then the mean head.
        slope: leaky-ReLU negative slope.

    Returns:
        ``act(obs [..., O]) -> action [..., A]`` (float32).
    """

    def act(obs: np.ndarray) -> np.ndarray:
        h = obs
        for kernel, bias in weights[:-1]:
            h = h @ kernel + bias
            h = np.maximum(h, slope * h)  # leaky ReLU for 0 < slope < 1
        kernel, bias = weights[-1]
        return np.tanh(h @ kernel + bias)

    return act


def _numpy_weights(params) -> list[tuple[np.ndarray, np.ndarray]]:
    """Flax actor parameters -> ``[(kernel, bias)]``, torso first, mean head last."""
    p = params["params"]
    torso = p["MLP_0"]
    layers = [torso[f"Dense_{i}"] for i in range(len(torso))]
    layers.append(p["Dense_0"])  # the mean head (Dense_1 is the log-std head)
    return [(np.asarray(d["kernel"]), np.asarray(d["bias"])) for d in layers]


def _policies():
    """``(cfg, params, act_jax, act_np)``: the paper's actor, jitted and in numpy."""
    cfg = CLACConfig()  # the paper's network sizes
    actor = make_networks(cfg, ACTIONS).actor
    params = actor.init(jax.random.key(0), jnp.zeros((1, OBS_SIZE), jnp.float32))
    act_jax = jax.jit(lambda p, obs: deterministic_action(actor.apply(p, obs)[0]))
    return (
        cfg,
        params,
        act_jax,
        numpy_policy(_numpy_weights(params), cfg.leaky_relu_slope),
    )


def _rounds(fn, calls: int):
    """``calls`` single-sample calls in a row: one timed round (single calls are too
    short to time one by one)."""

    def run():
        for _ in range(calls):
            fn()

    return run


def sync_dispatch_latency(*, single_calls: int, repeats: int) -> dict:
    """Single-sample latency with JAX's asynchronous CPU dispatch switched off.

    By default XLA:CPU runs a call on its own threads and the caller waits for them;
    on a busy machine waking those threads dominates a 150 k-FLOP forward pass.
    ``jax_cpu_enable_async_dispatch=False`` runs the call in the caller's thread, but
    the flag is read only when the CPU backend starts, so this figure is measured in a
    child process (this module run as a script), numpy interleaved there too.
    """
    experiments = str(Path(__file__).resolve().parents[1])
    path = os.pathsep.join(p for p in (experiments, os.environ.get("PYTHONPATH")) if p)
    proc = subprocess.run(
        [sys.executable, "-m", "cpubench.policy", str(single_calls), str(repeats)],
        capture_output=True,
        text=True,
        env={**os.environ, "PYTHONPATH": path},
        timeout=600,
    )
    name = "numpy forward pass (same child process)"
    if proc.returncode != 0:
        reason = f"child process failed: {proc.stderr.strip()[-500:]}"
        return figure(None, "us", "lower", missing_peer(name, reason), reason=reason)
    got = json.loads(proc.stdout)
    numpy_us = peer(name, got["numpy"][0], "us", got["numpy"][1])
    return figure(
        got["jax"][0], "us", "lower", numpy_us, best=got["jax"][1],
        note="host to host as single_sample_latency, with "
        "jax_cpu_enable_async_dispatch=False set before the backend starts",
    )  # fmt: skip


def _sync_child(single_calls: int, repeats: int) -> None:
    """Child of :func:`sync_dispatch_latency`: prints ``{"jax": [median, best],
    "numpy": [median, best]}`` in microseconds."""
    jax.config.update("jax_cpu_enable_async_dispatch", False)  # before any computation
    _, params, act_jax, act_np = _policies()
    obs1 = np.random.default_rng(0).normal(size=(OBS_SIZE,)).astype(np.float32)
    np.asarray(act_jax(params, obs1))  # compile
    t = time_interleaved(
        {
            "jax": _rounds(lambda: np.asarray(act_jax(params, obs1)), single_calls),
            "numpy": _rounds(lambda: act_np(obs1), single_calls),
        },
        repeats=repeats,
        work={"jax": single_calls, "numpy": single_calls},
    )
    print(json.dumps({k: list(v.per_item_us()) for k, v in t.items()}))


def bench_policy(
    *, batch: int, single_calls: int, repeats: int, matmul_n: int, child: bool = True
) -> dict:
    """Runs the policy-inference section.

    Args:
        batch: samples per batched call.
        single_calls: single-sample calls per timed round.
        repeats: timed rounds (each runs every variant once, interleaved).
        matmul_n: size n of the n x n x n float32 roofline matmul.
        child: also measure with async dispatch off (a child process, ~5 s).

    Returns:
        ``{"config": ..., "figures": {...}}``.
    """
    cfg, params, act_jax, act_np = _policies()
    rng = np.random.default_rng(0)
    obs1 = rng.normal(size=(OBS_SIZE,)).astype(np.float32)
    obs_b = rng.normal(size=(batch, OBS_SIZE)).astype(np.float32)
    obs_b_dev = jax.device_put(obs_b)
    agreement = float(
        np.max(np.abs(np.asarray(act_jax(params, obs_b_dev)) - act_np(obs_b)))
    )
    obs1_dev = jax.device_put(obs1)
    np.asarray(act_jax(params, obs1))  # compile the single-sample shape

    a = jax.device_put(rng.normal(size=(matmul_n, matmul_n)).astype(np.float32))
    b = jax.device_put(rng.normal(size=(matmul_n, matmul_n)).astype(np.float32))
    a_np, b_np = np.asarray(a), np.asarray(b)
    matmul = jax.jit(jnp.matmul)
    jax.block_until_ready(matmul(a, b))
    gflop_mm = 2e-9 * matmul_n**3

    # Single sample, host to host: what a real-time caller pays per sample.
    def single(fn):
        return _rounds(fn, single_calls)

    t = time_interleaved(
        {
            "single_jax": single(lambda: np.asarray(act_jax(params, obs1))),
            "single_resident": single(blocking(act_jax, params, obs1_dev)),
            "single_np": single(lambda: act_np(obs1)),
            "batch_jax": blocking(act_jax, params, obs_b_dev),
            "batch_np": lambda: act_np(obs_b),
            "matmul_jax": blocking(matmul, a, b),
            "matmul_np": lambda: a_np @ b_np,
        },
        repeats=repeats,
        work={
            "single_jax": single_calls,
            "single_resident": single_calls,
            "single_np": single_calls,
            "batch_jax": batch,
            "batch_np": batch,
            "matmul_jax": gflop_mm,
            "matmul_np": gflop_mm,
        },
    )
    single_jax, single_np = t["single_jax"], t["single_np"]
    batch_jax, batch_np, mm_jax, mm_np = (
        t["batch_jax"],
        t["batch_np"],
        t["matmul_jax"],
        t["matmul_np"],
    )

    h1, h2 = cfg.actor_hidden_sizes
    flops_sample = 2.0 * (OBS_SIZE * h1 + h1 * h2 + h2 * ACTIONS)
    lat_j, lat_j_best = single_jax.per_item_us()
    lat_n, lat_n_best = single_np.per_item_us()
    lat_r, lat_r_best = t["single_resident"].per_item_us()
    thr_j, thr_j_best = batch_jax.rate()
    thr_n, thr_n_best = batch_np.rate()
    roof, roof_best = mm_jax.rate()
    _, np_gflops_best = mm_np.rate()
    pol_gflops = thr_j * flops_sample * 1e-9
    pol_gflops_best = thr_j_best * flops_sample * 1e-9
    return {
        "config": {
            "network": f"{OBS_SIZE} -> {h1} -> {h2} -> {ACTIONS} (mean head), "
            f"leaky ReLU {cfg.leaky_relu_slope}, tanh(mean), float32",
            "batch": batch,
            "single_calls": single_calls,
            "repeats": repeats,
            "flops_per_sample": flops_sample,
            "matmul_n": matmul_n,
            "max_abs_diff_jax_vs_numpy": agreement,
        },
        "figures": {
            "single_sample_latency": figure(
                lat_j,
                "us",
                "lower",
                peer("numpy forward pass", lat_n, "us", lat_n_best),
                best=lat_j_best,
                note="host numpy obs in, jitted call, host action out",
            ),
            "single_sample_latency_resident": figure(
                lat_r,
                "us",
                "lower",
                peer("numpy forward pass", lat_n, "us", lat_n_best),
                best=lat_r_best,
                note="observation already on the device, output not copied back: "
                "the dispatch and execution cost alone",
            ),
            "single_sample_latency_sync_dispatch": (
                sync_dispatch_latency(single_calls=single_calls, repeats=repeats)
                if child
                else skipped("--quick: the child process costs a JAX start-up")
            ),
            "batched_throughput": figure(
                thr_j,
                "samples/s",
                "higher",
                peer("numpy forward pass", thr_n, "samples/s", thr_n_best),
                best=thr_j_best,
                batch=batch,
            ),
            # A roofline is a peak: both sides are read at their fastest repeat (on a
            # shared machine a median matmul can fall below the policy's median).
            "batched_gflops": figure(
                pol_gflops_best,
                "GFLOP/s",
                "higher",
                peer(
                    f"float32 matmul roofline (jax, n={matmul_n}), fastest repeat",
                    roof_best,
                    "GFLOP/s",
                    median=roof,
                    numpy_1_thread_gflops_best=np_gflops_best,
                ),
                median=pol_gflops,
                note="fastest repeats; ratio = fraction of the roofline reached by "
                "the batched policy",
            ),
        },
    }


if __name__ == "__main__":
    _sync_child(int(sys.argv[1]), int(sys.argv[2]))
