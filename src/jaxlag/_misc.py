"""Small helpers with no jaxlag dependency."""

import jax
import jax.core


def is_concrete(tree) -> bool:
    """Whether no leaf of ``tree`` is a tracer (the values are known on the host)."""
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))
