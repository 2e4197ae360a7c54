"""experiments/bench_deploy.py's kernel count of a compiled program, and the order
in which it interleaves the streams it times."""

from __future__ import annotations

import sys
from pathlib import Path

import jax
import jax.numpy as jnp

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "experiments"))
from bench_deploy import _per_row, compiled_ops  # noqa: E402


def _ops(fn, *args) -> dict:
    return compiled_ops(jax.jit(fn).lower(*args).compile().as_text())


def test_a_loop_in_the_main_computation_is_counted_with_its_trips():
    def looped(x):
        return jax.lax.fori_loop(0, 7, lambda i, v: jnp.sin(v * v + i), x)

    ops = _ops(looped, jnp.ones(3))
    (loop,) = ops["loops"]
    assert loop["trips"] == 7 and loop["every_call"] and loop["body_ops"] >= 1
    assert ops["entry"] >= 1  # the loop itself


def test_a_loop_in_a_branch_is_not_run_every_call():
    def branched(flag, x):
        return jax.lax.cond(
            flag,
            lambda v: jax.lax.fori_loop(0, 5, lambda i, u: jnp.sin(u) + i, v),
            lambda v: v * 2.0,
            x,
        )

    ops = _ops(branched, jnp.bool_(True), jnp.ones(3))
    assert [(lp["trips"], lp["every_call"]) for lp in ops["loops"]] == [(5, False)]


def test_parameters_constants_and_tuples_are_not_kernels():
    # one fused kernel; its parameter, constant and result tuple are none
    ops = _ops(lambda a: jnp.sin(a) + 2.0, jnp.ones(3))
    assert ops == {"entry": 1, "loops": []}


def test_streams_are_interleaved_in_blocks_and_each_sees_its_rows_in_order():
    calls = []
    fns = {name: (lambda t, name=name: calls.append((name, t))) for name in "ab"}
    out = _per_row(fns, rows=8, block=3)
    assert set(out) == {"a", "b"} and all(v["median_us"] >= 0 for v in out.values())
    timed = calls[2:]  # after each stream's compiling call at row 0
    assert [n for n, _ in timed] == list("aaabbbaaabbbab")
    for name in "ab":
        assert [t for n, t in timed if n == name] == list(range(1, 8))
    calls.clear()
    _per_row(fns, rows=4)  # row by row, the default
    assert [n for n, _ in calls[2:]] == list("ababab")
