"""The ensemble kernel on ``(block, n)`` arrays (per-member save times or step counts).

The state lives in memory as structure of arrays, ``(n, B)`` with the members along the last
(lane) axis, so each coordinate of a block is one contiguous load; while computing, a block is
``(block, n)`` and the equations are the `BatchedField` of the XLA loop, vmapped over the block.
The kernel's work is traced to jaxprs first, so that constants the equations create or close over
become kernel inputs (Pallas kernels may not capture arrays). Triton has no ``slice`` lowering
for these arrays: on a GPU this variant does not lower, and the caller falls back to XLA.
"""

from typing import Any

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
from jax.experimental import pallas as pl

from .kernel import KernelPlan, KernelProblem, KernelProgram, run_kernel
from .step import constant_step

__all__ = ["block_integrate"]


def _trace_block_work(problem: KernelProblem, settings, ts, y0, member_inputs, inner, uniform):
    """The work of the kernel as two functions of block-shaped values (SoA layout), traced to
    jaxprs: constants that the equations create while tracing (``jnp.stack`` of Python floats in
    a Lagrangian, values a user function closes over) become kernel inputs, which Pallas
    requires. Returns the jaxprs of the first stage and of one save interval, with the shape of
    the first stage and the tree of the carry."""
    tableau, block = settings.tableau, problem.block
    scalar = [jnp.ndim(x) == 0 for x in problem.shared_leaves]

    def unpack(member_vals, shared_vals):
        members = [jnp.moveaxis(v, -1, 0) for v in member_vals]
        return problem.field(members, [v.reshape(()) if s else v for v, s in zip(shared_vals, scalar)])

    def first(times, y, member_vals, shared_vals):
        return unpack(member_vals, shared_vals)(times[:, 0], y) if tableau.fsal else None

    def interval(k, y, f, times, counts, member_vals, shared_vals):
        block_field = unpack(member_vals, shared_vals)
        start = jax.lax.dynamic_index_in_dim(times, k, axis=1, keepdims=False)
        end = jax.lax.dynamic_index_in_dim(times, k + 1, axis=1, keepdims=False)
        m_k = jax.lax.dynamic_index_in_dim(counts, k, axis=0, keepdims=False)
        h = (end - start) / m_k.astype(end.dtype)

        def step(j, carry):
            t = start + j.astype(h.dtype) * h
            t1 = jnp.where(j + 1 == m_k, end, t + h)
            return constant_step(block_field, tableau, t, h, t1, carry, None if uniform else j < m_k)

        return jax.lax.fori_loop(0, inner, step, (y, f))

    def block_aval(x):
        return jax.ShapeDtypeStruct(x.shape[:-1] + (block,) if x.ndim else x.shape, x.dtype)

    data = (
        jax.ShapeDtypeStruct((block, problem.num_times), ts.dtype),
        jax.ShapeDtypeStruct((problem.num_times - 1, block), jnp.int32),
    )
    y_aval = (jax.ShapeDtypeStruct((block, problem.n), y0[0].dtype),) * 2
    member_avals = [block_aval(x) for x in member_inputs]
    shared_avals = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in problem.shared_leaves]
    first_jaxpr, f_shape = jax.make_jaxpr(first, return_shape=True)(
        data[0], y_aval, member_avals, shared_avals
    )
    interval_jaxpr, carry_shape = jax.make_jaxpr(interval, return_shape=True)(
        jax.ShapeDtypeStruct((), jnp.int32), y_aval, f_shape, *data, member_avals, shared_avals
    )
    return first_jaxpr, f_shape, interval_jaxpr, jax.tree.structure(carry_shape)


class _BlockProgram(KernelProgram):
    """A program of the kernel on ``(block, n)`` arrays: loads its block (transposed from the
    structure-of-arrays layout) and evaluates the traced work of `_trace_block_work`."""

    first_jaxpr: Any = eqx.field(static=True)
    interval_jaxpr: Any = eqx.field(static=True)
    f_def: Any = eqx.field(static=True)
    carry_def: Any = eqx.field(static=True)
    consts_scalar: list[bool] = eqx.field(static=True)
    num_members: int = eqx.field(static=True)
    num_shared: int = eqx.field(static=True)
    batch: int = eqx.field(static=True)

    def start(self, refs):
        q_ref, qd_ref, ts_ref, m_ref = refs[:4]
        num_members, num_shared = self.num_members, self.num_shared
        member_vals = [r[...] for r in refs[4:num_members]]
        shared_vals = [r[...] for r in refs[num_members : num_members + num_shared]]
        const_refs = refs[num_members + num_shared :]
        const_vals = [r[...].reshape(()) if s else r[...] for r, s in zip(const_refs, self.consts_scalar)]
        num_first = len(self.first_jaxpr.consts)
        times = ts_ref[...].T  # (block, T)
        counts = m_ref[...]  # (T-1, block)
        y = (q_ref[...].T, qd_ref[...].T)  # (block, n) while computing
        flat_data = jax.tree.leaves((times, counts, member_vals, shared_vals))
        f0 = jax.core.eval_jaxpr(
            self.first_jaxpr.jaxpr,
            const_vals[:num_first],
            *jax.tree.leaves((times, y, member_vals, shared_vals)),
        )
        f0 = jax.tree.unflatten(self.f_def, f0)

        def advance(k, carry):
            out = jax.core.eval_jaxpr(
                self.interval_jaxpr.jaxpr, const_vals[num_first:], k, *jax.tree.leaves(carry), *flat_data
            )
            return jax.tree.unflatten(self.carry_def, out)

        return (y, f0), advance

    def store(self, out_refs, k, y):
        out_refs[0][k] = y[0].T
        out_refs[1][k] = y[1].T

    def collect(self, outs):
        return tuple(jnp.swapaxes(x[..., : self.batch], 1, 2) for x in outs)


def _block_plan(problem: KernelProblem, settings, ts, y0, steps_per_interval, inner, uniform) -> KernelPlan:
    """The kernel on ``(block, n)`` arrays, members along the last (lane) axis in memory."""

    def soa(x):  # structure of arrays: members on the last axis
        return jnp.moveaxis(problem.pad_members(x), 0, -1)

    member_inputs = [soa(x) for x in problem.member_leaves]
    inputs = [soa(y0[0]), soa(y0[1]), soa(ts), soa(jnp.asarray(steps_per_interval, jnp.int32))]
    inputs += member_inputs
    first_jaxpr, f_shape, interval_jaxpr, carry_def = _trace_block_work(
        problem, settings, ts, y0, member_inputs, inner, uniform
    )
    consts = [jnp.asarray(c) for c in (*first_jaxpr.consts, *interval_jaxpr.consts)]
    shared_in = [jnp.reshape(x, (1,)) if jnp.ndim(x) == 0 else x for x in problem.shared_leaves]
    consts_in = [c.reshape((1,)) if c.ndim == 0 else c for c in consts]
    program = _BlockProgram(
        first_jaxpr, interval_jaxpr, jax.tree.structure(f_shape), carry_def,
        [c.ndim == 0 for c in consts], len(inputs), len(shared_in), problem.batch,
    )  # fmt: skip

    def member_spec(x):
        lead = x.ndim - 1
        return pl.BlockSpec(x.shape[:-1] + (problem.block,), lambda i, lead=lead: (0,) * lead + (i,))

    def shared_spec(x):
        return pl.BlockSpec(x.shape, lambda i, nd=x.ndim: (0,) * nd)

    num_saves = problem.num_times - 1
    return KernelPlan(
        name="jaxlag_ensemble",
        inputs=inputs + shared_in + consts_in,
        in_specs=[member_spec(x) for x in inputs] + [shared_spec(x) for x in shared_in + consts_in],
        out_shape=[jax.ShapeDtypeStruct((num_saves, problem.n, problem.padded), y0[0].dtype)] * 2,
        out_specs=[pl.BlockSpec((num_saves, problem.n, problem.block), lambda i: (0, 0, i))] * 2,
        program=program,
    )


def block_integrate(field, settings, ts, y0, steps_per_interval, inner, uniform, interpret, block):
    """The kernel on ``(block, n)`` arrays: saved states (T−1, B, n) each for ``q`` and ``q̇``."""
    problem = KernelProblem.of(field, ts, y0, block)
    plan = _block_plan(problem, settings, ts, y0, steps_per_interval, inner, uniform)
    return run_kernel(plan, problem, interpret)
