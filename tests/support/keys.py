"""Whether a pytree holds a typed PRNG key (a calibrator state's noise key)."""

import jax


def has_prng_key(tree) -> bool:
    return any(
        jax.dtypes.issubdtype(leaf.dtype, jax.dtypes.prng_key)
        for leaf in jax.tree.leaves(tree)
    )
