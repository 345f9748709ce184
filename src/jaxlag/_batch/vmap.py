"""``method=jl.Vmap()``: ``jax.vmap`` of [`simulate`][jaxlag.simulate] over the batch."""

import dataclasses

import equinox as eqx
import jax
import numpy as np

from .. import _checks as checking
from .. import _compile as compilation
from .._misc import is_concrete
from .._options import SimulateOptions, default_option
from .._simulate import save_times_message, simulate
from .._trajectory import Trajectory
from .methods import AbstractBatchMethod, BatchProblem


class Vmap(AbstractBatchMethod):
    """``jax.vmap`` of [`simulate`][jaxlag.simulate]: every option of ``simulate`` (events,
    unilateral constraints, any diffrax solver, controller and adjoint), each member with its own
    solver loop inside one batched loop that runs until the slowest member has finished."""

    def simulate(self, problem: BatchProblem, options: SimulateOptions) -> Trajectory:
        p = problem
        ts = p.ts
        if ts is not None and ts.ndim == 2:
            raise ValueError(f"Per-member save times ts of shape {ts.shape} need method=jl.Ensemble().")
        # Members fail on their own (traj.failure per member); simulate_batch raises once,
        # naming the failed members, or not at all with throw=False.
        checks = default_option(options, "checks")
        concrete = is_concrete((p.q0, p.qd0, ts, p.batched_args, p.shared_args))
        initial_check = None
        if concrete and _checked_on_host(ts, options):
            text = save_times_message(np.asarray(ts))
            if text is not None:
                raise ValueError(text)
            checks = dataclasses.replace(checks, times=False)
            if checks.initial_state:
                initial_check = (np.asarray(ts)[0], float(checks.tolerance(p.q0.dtype)))
                checks = dataclasses.replace(checks, initial_state=False)
        run_options: SimulateOptions = {**options, "checks": checks, "throw": False}
        out, diagnostics = _run_batch(p, run_options, initial_check)
        if concrete:  # compiled initial-state checks raise while we wait for the result
            jax.block_until_ready(out.failure.code)
        out, diagnostics = p.unpad((out, diagnostics))
        if initial_check is not None:
            args = eqx.combine(p.batched_args, p.shared_args)
            checking.raise_for_initial_states(p.system, diagnostics, args, initial_check[1])
        return out


def _checked_on_host(ts, options: SimulateOptions) -> bool:
    """Whether the batch's checks can run on the host: plain save times ``ts`` (no ``t0``,
    ``t1``, ``saveat`` or ``dt0`` of another sign) and one process (every row readable)."""
    if ts is None or any(options.get(k) is not None for k in ("t0", "t1", "saveat")):
        return False
    dt0 = options.get("dt0")
    if dt0 is not None and not (is_concrete(dt0) and float(dt0) >= 0):
        return False
    return jax.process_count() == 1


def _constrain(tree, sharding):
    def place(x):
        if isinstance(x, jax.Array) and x.ndim >= 1:
            return jax.lax.with_sharding_constraint(x, sharding)
        return x

    return jax.tree.map(place, tree)


@compilation.filter_jit
def _run_batch(problem: BatchProblem, options: SimulateOptions, initial_check):
    """The vmapped simulation; with ``initial_check = (t0, tolerance)`` also every member's
    initial-state diagnostics, returned as values for the host to raise (no callback)."""
    p = problem
    # The trajectory's non-array leaves (the system's functions, an eqx.nn.MLP's activation in
    # args) go around vmap, which maps arrays only.
    box = {}

    def one(q, qd, member_args):
        member_args = eqx.combine(member_args, p.shared_args)
        traj, box["static"] = eqx.partition(
            simulate(p.system, q, qd, p.ts, args=member_args, **options), eqx.is_array
        )
        if initial_check is None:
            return traj, None
        t0, tolerance = initial_check
        return traj, checking.initial_state_diagnostics(p.system, q, qd, t0, member_args, tolerance)

    q_axis = 0 if p.q0.ndim == 2 else None
    qd_axis = 0 if p.qd0.ndim == 2 else None
    out, diagnostics = jax.vmap(one, in_axes=(q_axis, qd_axis, 0))(p.q0, p.qd0, p.batched_args)
    out = eqx.combine(out, box["static"])
    if p.sharding is not None:
        # The inputs arrive sharded along the batch axis; XLA's SPMD partitioner propagates that
        # through the vmapped program, so each device integrates its slice. (The batched solver
        # loop still agrees across devices on when to stop: a scalar all-reduce per step. A
        # shard_map with one loop per device would avoid it, but lineax's structure check fails
        # under shard_map for the event root finder, so events would not work.)
        out = _constrain(out, p.sharding)
    return out, diagnostics
