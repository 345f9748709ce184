r"""The ensemble loop as one fused Pallas kernel (constant steps).

``simulate_batch(..., method=jl.Ensemble(backend="pallas"))``. The batch is cut into blocks of
``block`` members; one Pallas program per block (grid ``(⌈B/block⌉,)``) loads its members' state
once, runs the **whole** constant-step integration (every save interval, every Runge–Kutta stage,
the projection of constrained systems) in a ``lax.fori_loop`` inside the kernel, and writes only
the saved states. The state lives in memory as structure of arrays, ``(n, B)`` with the members
along the last (lane) axis, so each coordinate of a block is one contiguous load.

The right-hand side inside the kernel is the same
`BatchedField` as in the XLA loop (the library's
equations of motion, vmapped over the block): the arithmetic is
identical, so results agree with the XLA loop to rounding. The kernel's work is traced to jaxprs
first, so that constants the equations create or close over become kernel inputs (Pallas kernels
may not capture arrays). Whether a given system's equations
lower to a GPU kernel (Triton / Mosaic GPU) depends on the operations autodiff produced; when they
do not, `integrate_batch` catches the lowering error,
warns and uses the XLA loop. When all members share their save times the kernel is *lane-wise*
(`_lanes_integrate`, `jaxlag.experimental._ensemble.lanes`): every state entry and
parameter is a 1-D column and the step of one member is evaluated on columns as elementwise code,
which is what the Triton
lowering accepts (checked with ``jax.export`` for CUDA, float64: double pendulum, constrained
pendulum, knife edge); otherwise the kernel works on ``(block, n)`` arrays (Triton has no
``slice`` lowering for those). With ``interpret=True`` (``backend="pallas-interpret"``) the
kernel runs in Pallas's interpreter on any backend: that is how CI checks it on CPU.

Derivatives: the kernel is a ``jax.custom_jvp`` whose tangent rule differentiates the XLA loop
(the same discrete scheme), so ``jax.jvp``/``jax.grad`` work and give the XLA loop's derivatives.
"""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton

from .integrate import constant_loop, rk_step, select
from .lanes import constant, lanewise

#: Members per Pallas program (a multiple of the 32-lane warp; 128 keeps registers in check).
BLOCK = 128


def _split_field(field):
    """``field``'s arrays as (per-member leaves, shared leaves) and a function rebuilding it."""
    per_member = (field.member_args, field.constant_mass)
    dynamic_members, static_members = eqx.partition(per_member, eqx.is_array)
    rest = eqx.tree_at(
        lambda f: (f.member_args, f.constant_mass), field, (None, None), is_leaf=lambda x: x is None
    )
    dynamic_shared, static_shared = eqx.partition(rest, eqx.is_array)

    def rebuild(members, shared):
        member_args, constant_mass = eqx.combine(members, static_members)
        base = eqx.combine(shared, static_shared)
        return eqx.tree_at(
            lambda f: (f.member_args, f.constant_mass),
            base,
            (member_args, constant_mass),
            is_leaf=lambda x: x is None,
        )

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

    # The work of the kernel as two functions of block-shaped values (SoA layout), traced here
    # to jaxprs: constants that the equations create while tracing (``jnp.stack`` of Python
    # floats in a Lagrangian, values a user function closes over) become kernel inputs, which
    # Pallas requires.
    def unpack(member_vals, shared_vals):
        block_members = jax.tree.unflatten(member_def, [jnp.moveaxis(v, -1, 0) for v in member_vals])
        block_shared = jax.tree.unflatten(
            shared_def, [v.reshape(()) if s else v for v, s in zip(shared_vals, scalar)]
        )
        return rebuild(block_members, block_shared)

    def first(times, y, member_vals, shared_vals):
        return unpack(member_vals, shared_vals)(times[:, 0], y) if fsal else None

    def interval(k, y, f, times, counts, member_vals, shared_vals):
        block_field = unpack(member_vals, shared_vals)
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
                y1 = select(active, y1, y)
                f_next = select(active, f_next, f) if fsal else f_next
            return y1, f_next

        return jax.lax.fori_loop(0, inner, step, (y, f))

    def block_aval(x):
        shape = x.shape[:-1] + (block,) if x.ndim else x.shape
        return jax.ShapeDtypeStruct(shape, x.dtype)

    times_aval = jax.ShapeDtypeStruct((block, num_times), ts.dtype)
    counts_aval = jax.ShapeDtypeStruct((num_times - 1, block), jnp.int32)
    y_aval = (jax.ShapeDtypeStruct((block, n), y0[0].dtype),) * 2
    member_avals = [block_aval(x) for x in inputs[4:]]
    shared_avals = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(shared)]
    first_jaxpr, f_shape = jax.make_jaxpr(first, return_shape=True)(
        times_aval, y_aval, member_avals, shared_avals
    )
    interval_jaxpr, carry_shape = jax.make_jaxpr(interval, return_shape=True)(
        jax.ShapeDtypeStruct((), jnp.int32),
        y_aval,
        f_shape,
        times_aval,
        counts_aval,
        member_avals,
        shared_avals,
    )
    consts = [jnp.asarray(c) for c in (*first_jaxpr.consts, *interval_jaxpr.consts)]
    num_first = len(first_jaxpr.consts)
    carry_def = jax.tree.structure(carry_shape)
    consts_in = [c.reshape((1,)) if c.ndim == 0 else c for c in consts]
    consts_scalar = [c.ndim == 0 for c in consts]

    in_specs = (
        [member_spec(x) for x in inputs]
        + [shared_spec(x) for x in shared_leaves]
        + [shared_spec(x) for x in consts_in]
    )
    out_shape = [jax.ShapeDtypeStruct((num_times - 1, n, padded), y0[0].dtype)] * 2
    out_specs = [pl.BlockSpec((num_times - 1, n, block), lambda i: (0, 0, i))] * 2
    num_members_inputs = len(inputs)
    num_shared = len(shared_leaves)

    def kernel(*refs):
        q_ref, qd_ref, ts_ref, m_ref = refs[:4]
        member_vals = [r[...] for r in refs[4:num_members_inputs]]
        shared_vals = [r[...] for r in refs[num_members_inputs : num_members_inputs + num_shared]]
        const_refs = refs[num_members_inputs + num_shared : -2]
        out_q, out_qd = refs[-2:]
        const_vals = [r[...].reshape(()) if s else r[...] for r, s in zip(const_refs, consts_scalar)]
        times = ts_ref[...].T  # (block, T)
        counts = m_ref[...]  # (T-1, block)
        y = (q_ref[...].T, qd_ref[...].T)  # (block, n) while computing
        flat_data = jax.tree.leaves((times, counts, member_vals, shared_vals))
        f0 = jax.core.eval_jaxpr(
            first_jaxpr.jaxpr, const_vals[:num_first], *jax.tree.leaves((times, y, member_vals, shared_vals))
        )
        f0 = jax.tree.unflatten(jax.tree.structure(f_shape), f0)

        def one_interval(k, carry):
            out = jax.core.eval_jaxpr(
                interval_jaxpr.jaxpr, const_vals[num_first:], k, *jax.tree.leaves(carry), *flat_data
            )
            y, f = jax.tree.unflatten(carry_def, out)
            out_q[k] = y[0].T
            out_qd[k] = y[1].T
            return y, f

        jax.lax.fori_loop(jnp.int32(0), jnp.int32(num_times - 1), one_interval, (y, f0))

    out_q, out_qd = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(padded // block,),
        in_specs=in_specs,
        out_specs=out_specs,
        interpret=interpret,
        name="jaxlag_ensemble",
        # Triton: it lowers float64 (Mosaic GPU, the default GPU lowering, loads no f64).
        compiler_params=triton.CompilerParams(num_warps=4),
    )(*inputs, *shared_leaves, *consts_in)
    return tuple(jnp.swapaxes(x[..., :batch], 1, 2) for x in (out_q, out_qd))


def _lanes_integrate(field, settings, ts, y0, inner, interpret, block):
    """The kernel with lane-wise equations (`jaxlag.experimental._ensemble.lanes`): every
        state entry, parameter and per-member constant is its own 1-D column of the batch, and the
    Runge–Kutta step of one
    member, traced once, is evaluated on columns as straight-line elementwise code. Needs the
    same save times and step count for every member (they are read as scalars in the kernel)."""
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

    def member_field(t, y, member_vals, shared_vals):
        """The equations of one member, as a batch of one (the field's own code)."""
        one = rebuild(
            jax.tree.unflatten(member_def, [v[None] for v in member_vals]),
            jax.tree.unflatten(shared_def, shared_vals),
        )
        return jax.tree.map(lambda x: x[0], one(t[None], (y[0][None], y[1][None])))

    def member_step(t, h, t1, y, f0, member_vals, shared_vals):
        def batched(tb, yb):
            return jax.tree.map(
                lambda x: x[None],
                member_field(tb[0], jax.tree.map(lambda x: x[0], yb), member_vals, shared_vals),
            )

        y1, _, f_last = rk_step(
            batched,
            tableau,
            t[None],
            h[None],
            jax.tree.map(lambda x: x[None], y),
            jax.tree.map(lambda x: x[None], f0),
        )
        one = rebuild(
            jax.tree.unflatten(member_def, [v[None] for v in member_vals]),
            jax.tree.unflatten(shared_def, shared_vals),
        )
        y1 = one.project(t1[None], y1)
        return jax.tree.map(lambda x: x[0], (y1, f_last))

    scalar = jnp.zeros((), ts.dtype)
    example_y = (y0[0][0], y0[1][0])
    example_members = [x[0] for x in member_leaves]
    step_lanes = lanewise(
        member_step, scalar, scalar, scalar, example_y, example_y, example_members, shared_leaves
    )
    field_lanes = lanewise(member_field, scalar, example_y, example_members, shared_leaves)

    # Inputs: 1-D columns of length B (members on the lanes) for every entry of the state and of
    # the per-member parameters; shared values broadcast to columns too (traced, so they cannot
    # be literals); the save times as one small 1-D array read by scalar loads.
    def as_columns(x):  # (B, *shape) -> list of (B,) columns
        x = _pad_members(x, pad)
        return [x[(slice(None),) + index] for index in np.ndindex(*x.shape[1:])]

    state_columns = as_columns(y0[0]) + as_columns(y0[1])
    member_columns = [as_columns(x) for x in member_leaves]
    shared_columns = [as_columns(jnp.broadcast_to(x, (batch,) + jnp.shape(x))) for x in shared_leaves]
    flat_columns = state_columns + [c for cs in member_columns + shared_columns for c in cs]
    times = ts[0]
    column_spec = pl.BlockSpec((block,), lambda i: (i,))
    times_spec = pl.BlockSpec(times.shape, lambda i: (0,))
    out_shape = [jax.ShapeDtypeStruct((num_times - 1, padded), y0[0].dtype)] * (2 * n)
    out_specs = [pl.BlockSpec((num_times - 1, block), lambda i: (0, i))] * (2 * n)
    shapes = [x.shape[1:] for x in member_leaves], [jnp.shape(x) for x in shared_leaves]

    def kernel(*refs):
        column_refs, times_ref, out_refs = (
            refs[: len(flat_columns)],
            refs[len(flat_columns)],
            refs[len(flat_columns) + 1 :],
        )
        values = [r[...] for r in column_refs]
        state, rest = values[: 2 * n], values[2 * n :]

        def objects(flat, shape):
            out = np.empty(shape, dtype=object)
            for index, value in zip(np.ndindex(*shape), flat):
                out[index] = value
            return out

        member_objects, shared_objects, offset = [], [], 0
        for shape in shapes[0]:
            size = int(np.prod(shape, dtype=int))
            member_objects.append(objects(rest[offset : offset + size], shape))
            offset += size
        for shape in shapes[1]:
            size = int(np.prod(shape, dtype=int))
            shared_objects.append(objects(rest[offset : offset + size], shape))
            offset += size

        def as_state(flat):
            return (objects(flat[:n], (n,)), objects(flat[n:], (n,)))

        def flatten(y):
            return [
                jnp.broadcast_to(jnp.asarray(e, times.dtype), (block,)) for part in y for e in part.ravel()
            ]

        start_time = constant(times_ref[0])
        y = state
        f = flatten(field_lanes(start_time, as_state(y), member_objects, shared_objects)) if fsal else None

        def interval(k, carry):
            y, f = carry
            start, end = times_ref[k], times_ref[k + 1]
            h = (end - start) / inner

            def step(j, carry):
                y, f = carry
                t = start + j.astype(h.dtype) * h
                t1 = jnp.where(j + 1 == inner, end, t + h)
                if fsal:
                    f0 = as_state(f)
                else:
                    f0 = field_lanes(constant(t), as_state(y), member_objects, shared_objects)
                y1, f_last = step_lanes(
                    constant(t), constant(h), constant(t1), as_state(y), f0, member_objects, shared_objects
                )
                return flatten(y1), (flatten(f_last) if fsal else f)

            y, f = jax.lax.fori_loop(0, inner, step, (y, f))
            for ref, value in zip(out_refs, y):
                ref[k] = value
            return y, f

        jax.lax.fori_loop(jnp.int32(0), jnp.int32(num_times - 1), interval, (y, f))

    outs = pl.pallas_call(
        kernel,
        out_shape=out_shape,
        grid=(padded // block,),
        in_specs=[column_spec] * len(flat_columns) + [times_spec],
        out_specs=out_specs,
        interpret=interpret,
        name="jaxlag_ensemble_lanes",
        compiler_params=triton.CompilerParams(num_warps=4),
    )(*flat_columns, times)
    q = jnp.stack(outs[:n], axis=-1)[:, :batch]  # (T-1, B, n)
    qd = jnp.stack(outs[n:], axis=-1)[:, :batch]
    return q, qd


def integrate_pallas(field, settings, ts, y0, grid, interpret=False, block=None):
    """Constant steps in one kernel; returns what
        `integrate_ensemble` returns. Differentiable
    (the tangents are the XLA loop's, see the module docstring)."""
    steps_per_interval, inner, uniform, shared_times = grid
    block = BLOCK if block is None else block
    members, shared, rebuild = _split_field(field)
    lanewise = uniform and shared_times

    def kernel_integrate(field, ts, y0, steps):
        if lanewise:
            try:
                return _lanes_integrate(field, settings, ts, y0, inner, interpret, block)
            except NotImplementedError:  # a primitive without a lane-wise rule
                pass
        return _kernel_integrate(field, settings, ts, y0, steps, inner, uniform, interpret, block)

    @jax.custom_jvp
    def solve(members, shared, ts, y0, steps):
        return kernel_integrate(rebuild(members, shared), ts, y0, steps)

    @solve.defjvp
    def solve_jvp(primals, tangents):
        members, shared, ts, y0, steps = primals
        t_members, t_shared, t_ts, t_y0, _ = tangents

        def xla(members, shared, ts, y0):
            return constant_loop(rebuild(members, shared), settings, ts, y0, steps, inner, uniform)[0]

        out = kernel_integrate(rebuild(members, shared), ts, y0, steps)
        _, tangent_out = jax.jvp(xla, (members, shared, ts, y0), (t_members, t_shared, t_ts, t_y0))
        return out, tangent_out

    saved = solve(members, shared, ts, y0, steps_per_interval)
    counts = jnp.sum(jnp.asarray(steps_per_interval, jnp.int32), axis=1, dtype=jnp.int32)
    stats = {"num_steps": counts, "num_accepted_steps": counts, "num_rejected_steps": jnp.zeros_like(counts)}
    return saved, stats, jnp.ones(counts.shape, bool)
