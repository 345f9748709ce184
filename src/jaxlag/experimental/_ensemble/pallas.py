r"""The ensemble loop as one fused Pallas kernel (constant steps).

``simulate_batch(..., method=jl.Ensemble(backend="pallas"))``. The batch is cut into blocks of
``block`` members; one Pallas program per block (grid ``(⌈B/block⌉,)``) loads its members' state
once, runs the **whole** constant-step integration (every save interval, every Runge–Kutta stage,
the projection of constrained systems) in a ``lax.fori_loop`` inside the kernel, and writes only
the saved states (`jaxlag.experimental._ensemble.kernel`, shared by both variants).

The right-hand side inside the kernel is the library's equations of motion, the same code as in
the XLA loop: the arithmetic is identical, so results agree with the XLA loop to rounding.
Whether a given system's equations lower to a GPU kernel (Triton / Mosaic GPU) depends on the
operations autodiff produced; when they do not, `integrate_batch` catches the lowering error,
warns and uses the XLA loop. When all members share their save times the kernel is *lane-wise*
(`jaxlag.experimental._ensemble.lane_kernel`): every state entry and parameter is a 1-D column
and the step of one member is evaluated on columns as elementwise code, which is what the Triton
lowering accepts; otherwise the kernel works on ``(block, n)`` arrays
(`jaxlag.experimental._ensemble.block_kernel`). With ``interpret=True``
(``backend="pallas-interpret"``) the kernel runs in Pallas's interpreter on any backend: that is
how CI checks it on CPU.

Derivatives: the kernel is a ``jax.custom_jvp`` whose tangent rule differentiates the XLA loop
(the same discrete scheme), so ``jax.jvp``/``jax.grad`` work and give the XLA loop's derivatives.
"""

import jax
import jax.numpy as jnp

from .block_kernel import block_integrate
from .constant import constant_loop, step_counts
from .kernel import split_field
from .lane_kernel import lanes_integrate

__all__ = ["BLOCK", "integrate_pallas"]

#: Members per Pallas program (a multiple of the 32-lane warp; 128 keeps registers in check).
BLOCK = 128


def integrate_pallas(field, settings, ts, y0, grid, interpret=False, block=None):
    """Constant steps in one kernel; returns what `integrate_ensemble` returns. Differentiable
    (the tangents are the XLA loop's, see the module docstring)."""
    steps_per_interval, inner, uniform, shared_times = grid
    block = BLOCK if block is None else block
    members, shared, rebuild = split_field(field)
    lanewise = uniform and shared_times

    def kernel_integrate(field, ts, y0, steps):
        if lanewise:
            try:
                return lanes_integrate(field, settings, ts, y0, inner, interpret, block)
            except NotImplementedError:  # a primitive without a lane-wise rule
                pass
        return block_integrate(field, settings, ts, y0, steps, inner, uniform, interpret, block)

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
    stats = step_counts(steps_per_interval)
    return saved, stats, jnp.ones(stats["num_steps"].shape, bool)
