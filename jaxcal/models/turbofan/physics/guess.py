"""Newton start points: a small table of solved balances over (fan speed demand, Mach).

In corrected quantities a two-spool turbofan's operating point depends mostly on the
corrected fan speed and the flight Mach number (ram and nozzle pressure ratios);
altitude, off-standard days and health modifiers move it only a little. Starting Newton
from the design point converges over most of the envelope but not at flight idle, so the
table is built once per design by *continuation*: from the design point along Mach at
100 % demand, then along the fan-speed demand for each Mach column, each solve
warm-started from the previous one. :func:`initial_guess` interpolates it bilinearly.
The table is stored with the fitted design constants, so loading an engine costs
nothing.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

from jaxcal.models.turbofan.physics import cycle, solver
from jaxcal.models.turbofan.physics.atmosphere import isa_total_temperature
from jaxcal.models.turbofan.physics.design import (
    DesignPoint,
    EngineDesign,
    schedule_coefficients,
)

PCN_GRID = np.arange(54.0, 108.01, 2.0)  # % corrected fan speed demand
MACH_GRID = np.linspace(0.0, 0.9, 7)
_MACH_SUBSTEPS = 8


@struct.dataclass
class GuessTable:
    """z at the grid nodes, [len(PCN_GRID), len(MACH_GRID), 9]."""

    z: jnp.ndarray


def tra_for_pcn(d: EngineDesign, pcn):
    """Invert the TRA -> PCNfR_dmd schedule (monotone quadratic) by Newton on u."""
    c0, c1, c2 = schedule_coefficients(d)
    u = jnp.clip((pcn - c0) / (c1 + c2), 0.0, 1.5)
    for _ in range(8):
        f = c0 + c1 * u + c2 * u**2 - pcn
        u = u - f / (c1 + 2.0 * c2 * u)
    return 100.0 * u


def _residual(z, params):
    d, dp, w = params
    th = jnp.zeros(10, w.dtype)
    return cycle.balance(d, dp, w, th, jnp.zeros(cycle.NUM_EFFECTS, w.dtype), z)[0]


def build_guess_table(d: EngineDesign, dp: DesignPoint) -> GuessTable:
    """Solve the balance on the (PCN_GRID x MACH_GRID) grid by continuation
    (sea level)."""
    cfg = solver.SolverConfig(max_iter=30)
    pcn = jnp.asarray(PCN_GRID)
    i100 = int(np.argmin(np.abs(PCN_GRID - 100.0)))

    def w_of(p, m):
        alt = jnp.zeros_like(m)
        return jnp.stack([alt, m, tra_for_pcn(d, p), isa_total_temperature(alt, m)])

    def march(z0, path):
        def step(z, pm):
            z_new, info = solver.solve(_residual, z, (d, dp, w_of(pm[0], pm[1])), cfg)
            return z_new, z_new

        return jax.lax.scan(step, z0, path)

    def column(mach):
        frac = jnp.linspace(0.0, 1.0, _MACH_SUBSTEPS + 1)[1:]
        path_m = jnp.stack(
            [jnp.full_like(frac, pcn[i100]), d.mach_d + frac * (mach - d.mach_d)], 1
        )
        z100, _ = march(jnp.zeros(cycle.NUM_UNKNOWNS), path_m)
        down = jnp.stack([pcn[:i100][::-1], jnp.full((i100,), mach)], 1)
        up = jnp.stack(
            [pcn[i100 + 1 :], jnp.full((len(PCN_GRID) - i100 - 1,), mach)], 1
        )
        _, z_down = march(z100, down)
        _, z_up = march(z100, up)
        return jnp.concatenate([z_down[::-1], z100[None], z_up], 0)

    z = jax.vmap(column, out_axes=1)(jnp.asarray(MACH_GRID))
    return GuessTable(z=jax.lax.stop_gradient(z))


def initial_guess(table: GuessTable, pcn, mach):
    """Bilinear interpolation of the table at (PCNfR_dmd %, Mach), clamped at the
    edges."""
    fp = jnp.clip(
        (pcn - PCN_GRID[0]) / (PCN_GRID[1] - PCN_GRID[0]), 0.0, len(PCN_GRID) - 1.0
    )
    fm = jnp.clip(
        (mach - MACH_GRID[0]) / (MACH_GRID[1] - MACH_GRID[0]), 0.0, len(MACH_GRID) - 1.0
    )
    i0 = jnp.clip(jnp.floor(fp).astype(jnp.int32), 0, len(PCN_GRID) - 2)
    j0 = jnp.clip(jnp.floor(fm).astype(jnp.int32), 0, len(MACH_GRID) - 2)
    a, b = fp - i0, fm - j0
    z = table.z
    return (
        (1 - a) * (1 - b) * z[i0, j0]
        + a * (1 - b) * z[i0 + 1, j0]
        + (1 - a) * b * z[i0, j0 + 1]
        + a * b * z[i0 + 1, j0 + 1]
    )
