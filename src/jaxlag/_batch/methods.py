"""How [`simulate_batch`][jaxlag.simulate_batch] integrates a batch: the abstract method and the problem
that every method receives (``method=None``: chosen by ``simulate_batch``)."""

import abc

import equinox as eqx
import jax
from jax.sharding import NamedSharding
from jaxtyping import Array, Float, PyTree

from .._custom_types import Args
from .._options import SimulateOptions
from .._system import System
from .._trajectory import Trajectory


class BatchProblem(eqx.Module):
    """A batch as [`simulate_batch`][jaxlag.simulate_batch] prepared it: checked, placed on the devices
    of ``sharding`` (``None``: one device) and padded with ``pad`` copies of the last member to
    a multiple of the number of shards, ``size`` real members before the padding.

    ``q0``, ``qd0``: ``(B, n)`` per member or ``(n,)`` shared; ``ts``: ``(T,)`` shared,
    ``(B, T)`` per member, or ``None`` (``t0``/``t1``/``saveat`` among the options);
    ``batched_args``: the ``args`` leaves with a leading batch axis, ``shared_args`` the others
    (``eqx.combine`` gives one member's ``args``)."""

    system: System
    q0: Float[Array, "batch n"] | Float[Array, " n"]
    qd0: Float[Array, "batch n"] | Float[Array, " n"]
    ts: Float[Array, "batch times"] | Float[Array, " times"] | None
    batched_args: Args
    shared_args: Args
    size: int = eqx.field(static=True)
    pad: int = eqx.field(static=True)
    sharding: NamedSharding | None = eqx.field(static=True)

    def unpad(self, tree: PyTree) -> PyTree:
        """``tree`` without the padded members (the leading axis of its arrays cut to ``size``)."""
        if not self.pad:
            return tree
        return jax.tree.map(lambda x: x[: self.size] if isinstance(x, jax.Array) else x, tree)


class AbstractBatchMethod(eqx.Module):
    """How [`simulate_batch`][jaxlag.simulate_batch] integrates the batch: [`Vmap`][jaxlag.Vmap] or
    [`Ensemble`][jaxlag.Ensemble]. (``method=None`` picks one; see ``simulate_batch``.)

    A method implements `simulate`; ``simulate_batch`` prepares the
    `BatchProblem` before and raises for the failed members after it."""

    @abc.abstractmethod
    def simulate(self, problem: BatchProblem, options: SimulateOptions) -> Trajectory:
        """Every member of ``problem`` simulated with the options of [`simulate`][jaxlag.simulate]
        given in ``options`` (those left out: ``simulate``'s defaults): a
        [`Trajectory`][jaxlag.Trajectory] with a leading batch axis of ``problem.size`` members,
        the padding dropped, whose failed members are recorded in ``failure`` (not raised).
        Invalid input, including the initial states, raises here."""
