"""The members of a batched failure record on the host: which failed, one member's values, and
the prefix of a batched message. Shared by the eager checks (``jaxlag._checks``) and the
diagnosis of a run (``jaxlag._diagnosis``)."""

import jax
import numpy as np

__all__ = ["batch_prefix", "failed_members", "member"]


def member(tree, index):
    """Member ``index`` of a batched host pytree. Leaves carry the batch axes first, of full size
    or of size 1 (shared by every member)."""

    def take(x):
        x = np.asarray(x)
        return x[tuple(i if x.shape[k] > 1 else 0 for k, i in enumerate(index))]

    return jax.tree.map(take, tree)


def failed_members(flags):
    """Indices (tuples) of the batch members whose flag is set (``[()]`` unbatched)."""
    flags = np.asarray(flags)
    if flags.ndim == 0:
        return [()] if bool(flags) else []
    return [tuple(int(i) for i in index) for index in zip(*np.nonzero(flags))]


def batch_prefix(index, flags, members) -> str:
    """``"3 of 64 batch members failed (first: member [5])."`` or ``""`` when unbatched."""
    if not index:
        return ""
    where = ", ".join(str(i) for i in index)
    return (
        f"{len(members)} of {np.asarray(flags).size} batch members failed (first: member "
        f"[{where}]). Member [{where}]: "
    )
