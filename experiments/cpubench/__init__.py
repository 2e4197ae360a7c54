"""Sections of the CPU throughput benchmark run by ``experiments/bench_cpu.py``.

One module per section (policy inference, RL training, UKF, engine, end to end) and
:mod:`cpubench.measure` with the timing, steal-time and figure helpers they share.
Each section returns a dict of *figures*: a measured value next to its peer and the
ratio, or the reason why the peer has no number. Experiments code: nothing in
``jaxcal`` imports it.
"""
