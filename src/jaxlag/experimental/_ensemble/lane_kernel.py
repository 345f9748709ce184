"""The lane-wise ensemble kernel (all members share their save times and step counts).

Every state entry, parameter and per-member constant is its own 1-D column of the batch, and the
Runge–Kutta step of one member, traced once, is evaluated on columns as straight-line elementwise
code (`jaxlag.experimental._ensemble.lanes`): what the Triton lowering accepts (checked with
``jax.export`` for CUDA, float64: double pendulum, constrained pendulum, knife edge).
"""

import functools
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.experimental import pallas as pl

from .kernel import KernelPlan, KernelProblem, KernelProgram, run_kernel
from .lanes import constant, lanewise
from .step import rk_step

__all__ = ["lanes_integrate"]


def _lane_equations(problem: KernelProblem, settings, ts, y0):
    """The field and the projected Runge–Kutta step of one member, as lane-wise functions of
    object arrays of columns (`lanewise`): ``(field_lanes, step_lanes)``."""
    tableau = settings.tableau

    def member_field(t, y, member_vals, shared_vals):
        """The equations of one member, as a batch of one (the field's own code)."""
        one = problem.field([v[None] for v in member_vals], shared_vals)
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
        y1 = problem.field([v[None] for v in member_vals], shared_vals).project(t1[None], y1)
        return jax.tree.map(lambda x: x[0], (y1, f_last))

    scalar = jnp.zeros((), ts.dtype)
    example_y = (y0[0][0], y0[1][0])
    example_members = [x[0] for x in problem.member_leaves]
    shared = problem.shared_leaves
    field_lanes = lanewise(member_field, scalar, example_y, example_members, shared)
    step_lanes = lanewise(member_step, scalar, scalar, scalar, example_y, example_y, example_members, shared)
    return field_lanes, step_lanes


def _objects(flat, shape):
    """The values ``flat`` as an object array of ``shape``."""
    out = np.empty(shape, dtype=object)
    for index, value in zip(np.ndindex(*shape), flat):
        out[index] = value
    return out


def _unflatten_columns(values, shapes):
    """Consecutive runs of the columns ``values`` as object arrays of the given ``shapes``."""
    out, offset = [], 0
    for shape in shapes:
        size = int(np.prod(shape, dtype=int))
        out.append(_objects(values[offset : offset + size], shape))
        offset += size
    return out


class _LaneProgram(KernelProgram):
    """A program of the lane-wise kernel: loads its columns, rebuilds the state and parameters
    as object arrays of columns and evaluates the lane-wise field and step on them."""

    field_lanes: Callable = eqx.field(static=True)
    step_lanes: Callable = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)
    inner: int = eqx.field(static=True)
    n: int = eqx.field(static=True)
    block: int = eqx.field(static=True)
    batch: int = eqx.field(static=True)
    num_columns: int = eqx.field(static=True)
    shapes: list[tuple[int, ...]] = eqx.field(static=True)
    num_members: int = eqx.field(static=True)
    dtype: Any = eqx.field(static=True)

    def as_state(self, flat):
        n = self.n
        return (_objects(flat[:n], (n,)), _objects(flat[n:], (n,)))

    def flatten(self, y):
        return [
            jnp.broadcast_to(jnp.asarray(e, self.dtype), (self.block,)) for part in y for e in part.ravel()
        ]

    def start(self, refs):
        values = [r[...] for r in refs[: self.num_columns]]
        times_ref = refs[self.num_columns]
        y, params = values[: 2 * self.n], _unflatten_columns(values[2 * self.n :], self.shapes)
        members, shared = params[: self.num_members], params[self.num_members :]
        f = None
        if self.fsal:
            f = self.flatten(self.field_lanes(constant(times_ref[0]), self.as_state(y), members, shared))
        return (y, f), functools.partial(self.advance, times_ref, members, shared)

    def advance(self, times_ref, members, shared, k, carry):
        """The steps of save interval ``k``, all members on the same times (scalar loads)."""
        fsal, inner, as_state = self.fsal, self.inner, self.as_state
        start, end = times_ref[k], times_ref[k + 1]
        h = (end - start) / inner

        def step(j, carry):
            y, f = carry
            t = start + j.astype(h.dtype) * h
            t1 = jnp.where(j + 1 == inner, end, t + h)
            f0 = as_state(f) if fsal else self.field_lanes(constant(t), as_state(y), members, shared)
            y1, f_last = self.step_lanes(
                constant(t), constant(h), constant(t1), as_state(y), f0, members, shared
            )
            return self.flatten(y1), (self.flatten(f_last) if fsal else f)

        return jax.lax.fori_loop(0, inner, step, carry)

    def store(self, out_refs, k, y):
        for ref, value in zip(out_refs, y):
            ref[k] = value

    def collect(self, outs):  # (T-1, B, n) each
        n, batch = self.n, self.batch
        return jnp.stack(outs[:n], axis=-1)[:, :batch], jnp.stack(outs[n:], axis=-1)[:, :batch]


def _lane_plan(problem: KernelProblem, settings, ts, y0, inner) -> KernelPlan:
    """The lane-wise kernel: every state entry and parameter a ``(block,)`` column."""
    n, block = problem.n, problem.block

    # Inputs: 1-D columns of length B (members on the lanes) for every entry of the state and of
    # the per-member parameters; shared values broadcast to columns too (traced, so they cannot
    # be literals); the save times as one small 1-D array read by scalar loads.
    def as_columns(x):  # (B, *shape) -> list of (B,) columns
        x = problem.pad_members(x)
        return [x[(slice(None),) + index] for index in np.ndindex(*x.shape[1:])]

    columns = [c for x in (*y0, *problem.member_leaves) for c in as_columns(x)]
    columns += [
        c
        for x in problem.shared_leaves
        for c in as_columns(jnp.broadcast_to(x, (problem.batch,) + jnp.shape(x)))
    ]
    shapes = [x.shape[1:] for x in problem.member_leaves] + [jnp.shape(x) for x in problem.shared_leaves]
    times = ts[0]
    program = _LaneProgram(
        *_lane_equations(problem, settings, ts, y0), settings.tableau.fsal, inner, n, block,
        problem.batch, len(columns), shapes, len(problem.member_leaves), times.dtype,
    )  # fmt: skip
    num_saves = problem.num_times - 1
    return KernelPlan(
        name="jaxlag_ensemble_lanes",
        inputs=[*columns, times],
        in_specs=[pl.BlockSpec((block,), lambda i: (i,))] * len(columns)
        + [pl.BlockSpec(times.shape, lambda i: (0,))],
        out_shape=[jax.ShapeDtypeStruct((num_saves, problem.padded), y0[0].dtype)] * (2 * n),
        out_specs=[pl.BlockSpec((num_saves, block), lambda i: (0, i))] * (2 * n),
        program=program,
    )


def lanes_integrate(field, settings, ts, y0, inner, interpret, block):
    """The kernel with lane-wise equations (`jaxlag.experimental._ensemble.lanes`): every
    state entry, parameter and per-member constant is its own 1-D column of the batch, and the
    Runge–Kutta step of one member, traced once, is evaluated on columns as straight-line
    elementwise code. Needs the same save times and step count for every member (they are read
    as scalars in the kernel)."""
    problem = KernelProblem.of(field, ts, y0, block)
    return run_kernel(_lane_plan(problem, settings, ts, y0, inner), problem, interpret)
