"""RL training throughput: our jitted CLAC (and SAC) against SBX's SAC.

Environment: the tracking MDP of :mod:`jaxcal.envs.tracking` with the paper's learned
simulator D as dynamics (:func:`~jaxcal.surrogate.model.surrogate_apply`, 3 x 100 ReLU,
freshly initialised) on a synthetic fleet of normalised (w, x) records with the
``cmapss`` run's sizes (14 sensors, 4 conditions, 1 parameter, 200-step windows). The
cost of a step or an update does not depend on the values, only on the sizes.

* ours: :func:`jaxcal.training.runner.make_train_chunk` (one ``jax.jit``, ``lax.scan``
  over iterations, environments vmapped, replay buffer on device), one update per
  iteration on a minibatch of 256, 2 x 256 networks: CLAC with the production
  loop's 16 parallel environments, and SAC with one environment (the same work per
  iteration as SBX: one env step, one update);
* peer: ``sbx.SAC`` (JAX Stable-Baselines) on the same environment through
  :class:`~jaxcal.envs.gym_wrapper.TrackingGymEnv`, 2 x 256 leaky-ReLU networks,
  twin critics, batch 256, one gradient step per env step; torch pinned to 1 thread.

Rounds alternate ours and the peer's runs
(:func:`cpubench.measure.time_interleaved`).
"""

from __future__ import annotations

import dataclasses
import functools

import jax
import numpy as np

from cpubench.measure import (
    concurrently,
    figure,
    missing_peer,
    peer,
    skipped,
    time_interleaved,
    try_import,
)
from jaxcal.agents.clac import make_clac
from jaxcal.agents.configs import CLACConfig, SACConfig
from jaxcal.agents.sac import make_sac
from jaxcal.envs.gym_wrapper import TrackingGymEnv
from jaxcal.envs.tracking import EnvConfig, make_env_params, make_tracking_env
from jaxcal.problem import Normalisation
from jaxcal.surrogate.model import (
    SurrogateConfig,
    init_surrogate_params,
    surrogate_apply,
)
from jaxcal.training.runner import RunnerConfig, init_runner, make_train_chunk

SENSORS, CONDITIONS, PARAMS = 14, 4, 1


@dataclasses.dataclass(frozen=True)
class TrainingSizes:
    """Sizes of the training section (``quick`` shrinks everything)."""

    hidden: tuple[int, ...] = (256, 256)
    batch_size: int = 256
    episode_length: int = 200
    unit_length: int = 1000
    num_envs: int = 16
    chunk_steps: int = 200  # iterations per timed chunk of ours
    peer_steps: int = 200  # env steps per timed SBX learn() call
    repeats: int = 3


QUICK_SIZES = TrainingSizes(
    hidden=(32, 32), batch_size=32, episode_length=20, unit_length=60, num_envs=4,
    chunk_steps=20, peer_steps=40, repeats=2,
)  # fmt: skip


def make_problem(sizes: TrainingSizes, seed: int = 0):
    """The tracking env on D and synthetic params: ``(env, env_params)``."""
    rng = np.random.default_rng(seed)
    units = 4
    w = rng.normal(size=(units, sizes.unit_length, CONDITIONS)).astype(np.float32)
    x = rng.normal(size=(units, sizes.unit_length, SENSORS)).astype(np.float32)
    lengths = np.full((units,), sizes.unit_length, np.int32)
    dyn = init_surrogate_params(
        jax.random.key(seed), CONDITIONS, SENSORS, PARAMS, SurrogateConfig()
    )
    stats = Normalisation.of(w.reshape(-1, CONDITIONS), x.reshape(-1, SENSORS), None)
    params = make_env_params(w, x, lengths, [-0.02], [0.0], dyn, stats=stats)
    cfg = EnvConfig(SENSORS, CONDITIONS, PARAMS, episode_length=sizes.episode_length)
    return make_tracking_env(surrogate_apply, cfg), params


def _chunk_runner(env, env_params, agent, sizes: TrainingSizes, num_envs: int):
    """A warmed-up ``run()`` advancing our runner by one chunk (blocking)."""
    cfg = RunnerConfig(
        num_envs=num_envs,
        num_steps_per_chunk=sizes.chunk_steps,
        batch_size=sizes.batch_size,
        buffer_size=max(50_000, 4 * num_envs * sizes.chunk_steps),
        warmup_steps=sizes.batch_size,
        min_buffer_size=sizes.batch_size,
    )
    chunk = jax.jit(make_train_chunk(env, agent, cfg), donate_argnums=0)
    init = jax.jit(init_runner, static_argnums=(1, 2, 4))  # eager init takes ~10 s
    state = {"runner": init(jax.random.key(1), env, agent, env_params, cfg)}
    # Two chunks before timing: the first compiles and fills the buffer past the
    # update threshold, so every timed iteration runs its update.
    for _ in range(2):
        state["runner"], _ = chunk(state["runner"], env_params)
    jax.block_until_ready(state["runner"])

    def run() -> None:
        updates_before = int(state["runner"].num_updates)
        state["runner"], metrics = chunk(state["runner"], env_params)
        jax.block_until_ready(metrics)
        # Every timed iteration must update, or the rate would flatter us.
        if int(state["runner"].num_updates) - updates_before != sizes.chunk_steps:
            raise RuntimeError("a timed chunk skipped updates")

    return run


def _sbx_runner(sbx, env, env_params, sizes: TrainingSizes):
    """SBX SAC warmed up: a ``run()`` learning ``peer_steps`` more steps per call, or
    the reason (a string) why SBX failed."""
    try:
        return _make_sbx_run(sbx, env, env_params, sizes)
    except Exception as err:  # a broken optional peer is reported, not fatal
        return f"sbx failed: {type(err).__name__}: {err}"


def _make_sbx_run(sbx, env, env_params, sizes: TrainingSizes):
    import flax.linen as nn

    model = sbx.SAC(
        "MlpPolicy",
        TrackingGymEnv(env, env_params, seed=0),
        learning_starts=sizes.batch_size,
        batch_size=sizes.batch_size,
        buffer_size=50_000,
        train_freq=1,
        gradient_steps=1,
        policy_kwargs={
            "net_arch": list(sizes.hidden),
            "activation_fn": functools.partial(nn.leaky_relu, negative_slope=0.2),
        },
        seed=0,
        verbose=0,
    )
    # Compile the policy and the update before timing (past learning_starts).
    model.learn(total_timesteps=sizes.batch_size + sizes.peer_steps)

    def run() -> None:
        model.learn(total_timesteps=sizes.peer_steps, reset_num_timesteps=False)

    return run


def bench_training(
    sizes: TrainingSizes, *, peers: bool = True, like_for_like: bool = True
) -> dict:
    """Runs the training section.

    Args:
        sizes: problem and timing sizes.
        peers: run SBX if it imports (False: the figures say the peer was disabled).
        like_for_like: also time our SAC with one environment (one more compilation).

    Returns:
        ``{"config": ..., "figures": ...}``: CLAC updates/s and env steps/s, SAC
        (1 env) updates/s, each against SBX SAC.
    """
    env, env_params = make_problem(sizes)
    nets = {"actor_hidden_sizes": sizes.hidden, "critic_hidden_sizes": sizes.hidden}
    clac = make_clac(CLACConfig(**nets), env.observation_size, env.action_size)
    sac = make_sac(SACConfig(**nets), env.observation_size, env.action_size)
    jobs = {"clac": lambda: _chunk_runner(env, env_params, clac, sizes, sizes.num_envs)}
    if like_for_like:
        jobs["sac_1env"] = lambda: _chunk_runner(env, env_params, sac, sizes, 1)
    reason = "optional peers disabled (--no-optional-peers)"
    if peers:
        # Imported here, not in a warm-up thread: try_import restores JAX flags.
        (sbx, reason), (torch, torch_reason) = try_import("sbx"), try_import("torch")
        reason = reason or torch_reason
        if sbx is not None and torch is not None:
            # torch only moves replay samples here; two threads thrash under load
            torch.set_num_threads(1)
            jobs["sbx"] = lambda: _sbx_runner(sbx, env, env_params, sizes)
    # Compile ours and warm SBX up side by side; timing starts after all are done.
    runners = dict(zip(jobs, concurrently(*jobs.values()), strict=True))
    if isinstance(runners.get("sbx"), str):  # SBX failed: its reason
        reason = runners.pop("sbx")
    work = {"clac": sizes.chunk_steps, "sac_1env": sizes.chunk_steps,
            "sbx": sizes.peer_steps}  # fmt: skip
    t = time_interleaved(runners, repeats=sizes.repeats, work=work)

    peer_name = "sbx.SAC through TrackingGymEnv (1 env, 1 update per step)"
    if "sbx" in t:
        sbx_rate, sbx_best = t["sbx"].rate()
        sbx_updates = peer(peer_name, sbx_rate, "updates/s", sbx_best)
        sbx_steps = peer(peer_name, sbx_rate, "env steps/s", sbx_best)
    else:
        sbx_updates = sbx_steps = missing_peer(peer_name, reason)
    clac_upd, clac_upd_best = t["clac"].rate()  # one update per iteration
    envs = sizes.num_envs
    ours = f"CLAC, {envs} envs, jitted lax.scan chunk"
    figures = {
        "clac_updates_per_s": figure(
            clac_upd, "updates/s", "higher", sbx_updates, best=clac_upd_best, ours=ours
        ),
        "clac_env_steps_per_s": figure(
            envs * clac_upd, "env steps/s", "higher", sbx_steps,
            best=envs * clac_upd_best, ours=ours,
        ),
    }  # fmt: skip
    if "sac_1env" in t:
        sac_upd, sac_upd_best = t["sac_1env"].rate()
        figures["sac_1env_updates_per_s"] = figure(
            sac_upd, "updates/s", "higher", sbx_updates, best=sac_upd_best,
            ours="SAC (twin Q), 1 env, one update per env step: SBX's loop",
        )  # fmt: skip
    else:
        figures["sac_1env_updates_per_s"] = skipped(
            "like-for-like SAC run skipped (--quick: one more compilation)"
        )
    return {
        "config": {
            **dataclasses.asdict(sizes),
            "dynamics": "surrogate D (3 x 100 ReLU), synthetic normalised data",
            "updates_per_iteration": 1,
            "observation_size": env.observation_size,
            "action_size": env.action_size,
        },
        "figures": figures,
    }
