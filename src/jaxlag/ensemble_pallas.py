r"""The ensemble loop as one fused Pallas kernel (constant steps).

``simulate_batch(..., method="ensemble", backend="pallas")``. The batch is cut into blocks of
``block`` members; one Pallas program per block (grid ``(⌈B/block⌉,)``) loads its members' state
once, runs the **whole** constant-step integration (every save interval, every Runge–Kutta stage,
the projection of constrained systems) in a ``lax.fori_loop`` inside the kernel, and writes only
the saved states. The state lives in memory as structure of arrays, ``(n, B)`` with the members
along the last (lane) axis, so each coordinate of a block is one contiguous load.

The right-hand side inside the kernel is the same :class:`~jaxlag.ensemble.BatchedField` as in
the XLA loop (the library's equations of motion, vmapped over the block): the arithmetic is
identical, so results agree with the XLA loop to rounding. Whether a given system's equations
lower to a GPU kernel (Triton / Mosaic GPU) depends on the operations autodiff produced; when they
do not, :func:`~jaxlag.ensemble_entry.run_ensemble` catches the lowering error, warns and uses the
XLA loop. With ``interpret=True`` (``backend="pallas-interpret"``) the kernel runs in Pallas's
interpreter on any backend: that is how CI checks it on CPU.

Derivatives: the kernel is a ``jax.custom_jvp`` whose tangent rule differentiates the XLA loop
(the same discrete scheme), so ``jax.jvp``/``jax.grad`` work and give the XLA loop's derivatives.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl

from .ensemble import _constant_loop, _select, rk_step

#: Members per Pallas program (a multiple of the 32-lane warp; 128 keeps registers in check).
BLOCK = 128


def _split_field(field):
    """``field``'s arrays as (per-member leaves, shared leaves) and a function rebuilding it."""
    per_member = (field.member_args, field.constant_mass)
    dynamic_members, static_members = eqx.partition(per_member, eqx.is_array)
    rest = eqx.tree_at(lambda f: (f.member_args, f.constant_mass), field, (None, None),
                       is_leaf=lambda x: x is None)
    dynamic_shared, static_shared = eqx.partition(rest, eqx.is_array)

    def rebuild(members, shared):
        member_args, constant_mass = eqx.combine(members, static_members)
        base = eqx.combine(shared, static_shared)
        return eqx.tree_at(lambda f: (f.member_args, f.constant_mass), base,
                           (member_args, constant_mass), is_leaf=lambda x: x is None)

    return dynamic_members, dynamic_shared, rebuild


def _pad_members(x, pad):
    if pad == 0:
        return x
    return jnp.concatenate([x, jnp.repeat(x[-1:], pad, axis=0)], axis=0)


def _kernel_integrate(field, settings, ts, y0, steps_per_interval, inner, uniform, interpret, block):
    """The Pallas call: saved states (T−1, B, n) each for ``q`` and ``q̇``."""
    tableau = settings.tableau
    fsal = tableau.fsal
    batch, num_times = ts.shape
    n = y0[0].shape[1]
    block = min(block, batch)
    pad = -batch % block
    padded = batch + pad
    members, shared, rebuild = _split_field(field)
    member_leaves, member_def = jax.tree.flatten(members)
    shared_leaves, shared_def = jax.tree.flatten(shared)

    # Structure of arrays: members on the last axis.
    def soa(x):
        return jnp.moveaxis(_pad_members(x, pad), 0, -1)

    inputs = [soa(y0[0]), soa(y0[1]), soa(ts), soa(jnp.asarray(steps_per_interval, jnp.int32))]
    inputs += [soa(x) for x in member_leaves]
    shared_leaves = [jnp.reshape(x, (1,)) if jnp.ndim(x) == 0 else x for x in shared_leaves]
    scalar = [jnp.ndim(x) == 0 for x in jax.tree.leaves(shared)]

    def member_spec(x):
        lead = x.ndim - 1
        return pl.BlockSpec(x.shape[:-1] + (block,), lambda i, lead=lead: (0,) * lead + (i,))

    def shared_spec(x):
        return pl.BlockSpec(x.shape, lambda i, nd=x.ndim: (0,) * nd)

    in_specs = [member_spec(x) for x in inputs] + [shared_spec(x) for x in shared_leaves]
    out_shape = [jax.ShapeDtypeStruct((num_times - 1, n, padded), y0[0].dtype)] * 2
    out_specs = [pl.BlockSpec((num_times - 1, n, block), lambda i: (0, 0, i))] * 2
    num_members_inputs = len(inputs)

    def kernel(*refs):
        q_ref, qd_ref, ts_ref, m_ref = refs[:4]
        member_refs = refs[4:num_members_inputs]
        shared_refs = refs[num_members_inputs:num_members_inputs + len(shared_leaves)]
        out_q, out_qd = refs[num_members_inputs + len(shared_leaves):]
        block_members = jax.tree.unflatten(
            member_def, [jnp.moveaxis(r[...], -1, 0) for r in member_refs])
        block_shared = jax.tree.unflatten(
            shared_def, [r[...].reshape(()) if s else r[...] for r, s in zip(shared_refs, scalar)])
        block_field = rebuild(block_members, block_shared)
        times = ts_ref[...].T                 # (block, T)
        counts = m_ref[...]                   # (T-1, block)
        y = (q_ref[...].T, qd_ref[...].T)     # (block, n) while computing

        def interval(k, carry):
            y, f = carry
            start = jax.lax.dynamic_index_in_dim(times, k, axis=1, keepdims=False)
            end = jax.lax.dynamic_index_in_dim(times, k + 1, axis=1, keepdims=False)
            m_k = jax.lax.dynamic_index_in_dim(counts, k, axis=0, keepdims=False)
            h = (end - start) / m_k.astype(end.dtype)

            def step(j, carry):
                y, f = carry
                t = start + j.astype(h.dtype) * h
                f0 = f if fsal else block_field(t, y)
                y1, _, f_last = rk_step(block_field, tableau, t, h, y, f0)
                t1 = jnp.where(j + 1 == m_k, end, t + h)
                y1 = block_field.project(t1, y1)
                f_next = f_last if fsal else f
                if not uniform:
                    active = j < m_k
                    y1 = _select(active, y1, y)
                    f_next = _select(active, f_next, f) if fsal else f_next
                return y1, f_next

            y, f = jax.lax.fori_loop(0, inner, step, (y, f))
            out_q[k] = y[0].T
            out_qd[k] = y[1].T
            return y, f

        f0 = block_field(times[:, 0], y) if fsal else None
        jax.lax.fori_loop(0, num_times - 1, interval, (y, f0))

    out_q, out_qd = pl.pallas_call(
        kernel, out_shape=out_shape, grid=(padded // block,), in_specs=in_specs,
        out_specs=out_specs, interpret=interpret, name="jaxlag_ensemble",
    )(*inputs, *shared_leaves)
    return tuple(jnp.swapaxes(x[..., :batch], 1, 2) for x in (out_q, out_qd))


def integrate_pallas(field, settings, ts, y0, grid, interpret=False, block=None):
    """Constant steps in one kernel; returns what :func:`~jaxlag.ensemble.integrate_ensemble`
    returns. Differentiable (the tangents are the XLA loop's, see the module docstring)."""
    steps_per_interval, inner, uniform = grid
    block = BLOCK if block is None else block
    members, shared, rebuild = _split_field(field)

    @jax.custom_jvp
    def solve(members, shared, ts, y0, steps):
        return _kernel_integrate(rebuild(members, shared), settings, ts, y0, steps, inner, uniform,
                                 interpret, block)

    @solve.defjvp
    def solve_jvp(primals, tangents):
        members, shared, ts, y0, steps = primals
        t_members, t_shared, t_ts, t_y0, _ = tangents

        def xla(members, shared, ts, y0):
            return _constant_loop(rebuild(members, shared), settings, ts, y0, steps, inner,
                                  uniform)[0]

        out = _kernel_integrate(rebuild(members, shared), settings, ts, y0, steps, inner, uniform,
                                interpret, block)
        _, tangent_out = jax.jvp(xla, (members, shared, ts, y0), (t_members, t_shared, t_ts, t_y0))
        return out, tangent_out

    saved = solve(members, shared, ts, y0, steps_per_interval)
    counts = jnp.sum(jnp.asarray(steps_per_interval, jnp.int32), axis=1, dtype=jnp.int32)
    stats = {"num_steps": counts, "num_accepted_steps": counts,
             "num_rejected_steps": jnp.zeros_like(counts)}
    return saved, stats, jnp.ones(counts.shape, bool)
