"""The two sweeps of Featherstone's algorithms over a tree, as `jax.lax.scan` over its links.

Links are numbered parents first, so one pass in link order reaches every parent before its
children (`descend`) and one pass in reverse reaches every child before its parent (`ascend`).
The scan's carry holds one row per link plus a last row for the world, indexed by the parent's
row: the program's size does not grow with the number of links (a 100-link chain compiles as
fast as a 2-link one), and each sweep costs O(links).
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import PyTree


def descend(parent_slot: np.ndarray, root: PyTree, step: Callable, xs: PyTree) -> PyTree:
    """``value_i = step(value_{parent(i)}, x_i)`` for the links in order; ``root`` is the
    world's value. Returns every link's value, stacked."""
    links = parent_slot.shape[0]
    init = jax.tree.map(lambda r: jnp.zeros((links + 1, *r.shape), r.dtype).at[links].set(r), root)

    def body(carry, x):
        i, slot, xi = x
        value = step(jax.tree.map(lambda c: c[slot], carry), xi)
        return jax.tree.map(lambda c, v: c.at[i].set(v), carry, value), value

    _, values = jax.lax.scan(body, init, (jnp.arange(links), jnp.asarray(parent_slot), xs))
    return values


def ascend(parent_slot: np.ndarray, own: PyTree, step: Callable, xs: PyTree) -> PyTree:
    """For the links in reverse order: ``(to_parent, y_i) = step(total_i, x_i)``, where
    ``total_i`` is the link's ``own`` value plus what its children passed up, and ``to_parent`` is
    added to the parent's total. Returns the ``y_i``, stacked in link order."""
    links = parent_slot.shape[0]
    init = jax.tree.map(lambda a: jnp.concatenate([a, jnp.zeros((1, *a.shape[1:]), a.dtype)]), own)

    def body(carry, x):
        i, slot, xi = x
        up, y = step(jax.tree.map(lambda c: c[i], carry), xi)
        return jax.tree.map(lambda c, u: c.at[slot].add(u), carry, up), y

    _, ys = jax.lax.scan(body, init, (jnp.arange(links), jnp.asarray(parent_slot), xs), reverse=True)
    return ys
