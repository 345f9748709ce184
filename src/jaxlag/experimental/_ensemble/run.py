"""One compiled ensemble run: an `EnsembleRun` (the batch and everything decided on the host) in,
a [`Trajectory`][jaxlag.Trajectory] with a leading batch axis and the initial-state diagnostics
out, under one ``jax.jit`` (`run`). The loop is the XLA one (`integrate_ensemble`) or the Pallas
kernel (`integrate_pallas`); `kernel_lowers` asks ahead whether the kernel compiles."""

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ... import _compile as compilation
from ..._batch.methods import BatchProblem
from ..._stabilization import Baumgarte, Projection
from ..._trajectory import Trajectory
from .integrate import ensemble_problem, integrate_ensemble
from .outcome import member_failures
from .pallas import integrate_pallas
from .settings import EnsembleSettings

__all__ = ["ConstantGrid", "EnsembleRun", "run", "kernel_lowers"]


class ConstantGrid(eqx.Module):
    """Constant steps: ``steps[b, k]`` equal steps in save interval ``k`` of member ``b``
    (`constant_grid`), ``inner`` their maximum,
    ``uniform`` whether every entry equals it and ``shared_times`` whether every member has
    the same save times (the lane-wise Pallas kernel)."""

    steps: Int[Array, "batch intervals"]
    inner: int = eqx.field(static=True)
    uniform: bool = eqx.field(static=True)
    shared_times: bool = eqx.field(static=True)

    def as_tuple(self):
        return self.steps, self.inner, self.uniform, self.shared_times


class EnsembleRun(eqx.Module):
    """One compiled ensemble run: the batch, its save times ``ts`` ``(B, T)`` (the first
    column the start), the loop's settings, the constant-step grid (``None``: adaptive) or the
    first step ``dt0``, and how the result is assembled (``keep_first``: the start is a save,
    as ``ts[0]`` is for ``jl.simulate``). ``check``: the initial-state check, ``"host"``
    (diagnostics returned), ``True`` (compiled in) or ``False``."""

    problem: BatchProblem
    ts: Float[Array, "batch times"]
    settings: EnsembleSettings
    grid: ConstantGrid | None
    dt0: Float[Array, ""] | None
    baumgarte: Baumgarte | None
    projection: Projection | None
    check: bool | str = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    keep_first: bool = eqx.field(static=True)


def _broadcast_members(tree, batch):
    def expand(x):
        if eqx.is_array(x):
            x = jnp.asarray(x)
            return jnp.broadcast_to(x, (batch,) + x.shape)
        return x

    return jax.tree.map(expand, tree)


def _integrate(run: EnsembleRun, backend: str):
    """The checked initial states and the loop: ``(y0, saved, failure, result, stats,
    diagnostics)``, the saves ``(q, q̇)`` each (T−1, B, n), the unreached ones ``inf``."""
    p, ts, settings = run.problem, run.ts, run.settings
    field, y0, diagnostics = ensemble_problem(
        p.system, p.q0, p.qd0, ts, p.batched_args, p.shared_args,
        run.baumgarte, run.projection, run.check, run.tolerance,
    )  # fmt: skip
    grid = None if run.grid is None else run.grid.as_tuple()
    if backend in ("pallas", "pallas-interpret"):
        saved, stats, _ = integrate_pallas(
            field, settings, ts, y0, grid, interpret=backend == "pallas-interpret"
        )
        record = None
    else:
        saved, stats, record = integrate_ensemble(field, settings, ts, y0, run.dt0, grid)
    saved, failure, result = member_failures(
        ts, y0, saved, stats, record, None if grid is None else grid[0], settings.max_steps
    )
    return y0, saved, failure, result, stats, diagnostics


def _shard(out: Trajectory, sharding) -> Trajectory:
    """Every batched array of ``out`` laid out along the batch's sharding."""
    if sharding is None:
        return out
    return jax.tree.map(
        lambda x: (
            jax.lax.with_sharding_constraint(x, sharding) if isinstance(x, jax.Array) and x.ndim >= 1 else x
        ),
        out,
    )


def run_impl(run: EnsembleRun, backend: str):
    """``(trajectory, diagnostics)`` of the batch: the saves as (B, T, n), the start first when
    ``run.keep_first``, every member's arguments and system arrays along the batch axis."""
    p, ts = run.problem, run.ts
    y0, saved, failure, result, stats, diagnostics = _integrate(run, backend)
    q, qd = (jnp.moveaxis(x, 0, 1) for x in saved)  # (B, T-1, n)
    if run.keep_first:
        q = jnp.concatenate([y0[0][:, None], q], axis=1)
        qd = jnp.concatenate([y0[1][:, None], qd], axis=1)
        t = ts
    else:
        t = ts[:, 1:]
    batch = q.shape[0]
    stats = {**stats, "max_steps": jnp.full((batch,), run.settings.max_steps, jnp.int32)}
    args = eqx.combine(p.batched_args, _broadcast_members(p.shared_args, batch))
    system_arrays, system_static = eqx.partition(p.system, eqx.is_array)
    system_arrays = _broadcast_members(system_arrays, batch)
    out = Trajectory(
        t, q, qd, args, stats, result, system_arrays,
        active=None, events=None, failure=failure, system_static=system_static,
    )  # fmt: skip
    return _shard(out, p.sharding), diagnostics


run = compilation.filter_jit(run_impl)


def kernel_lowers(run: EnsembleRun, backend: str) -> Exception | None:
    """Compile the Pallas variant from abstract shapes: ``None`` if it lowers, else the error.

    Done ahead of the real call so that a failure is caught here even when ``simulate_batch`` is
    traced inside the caller's own ``jax.jit`` (whose compilation would otherwise fail later).
    """
    dynamic, static = eqx.partition(run, eqx.is_array)
    spec = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), dynamic)
    try:
        compilation.jit(lambda d: run_impl(eqx.combine(d, static), backend)).lower(spec).compile()
    except Exception as error:  # noqa: BLE001 - any lowering failure: the XLA loop is exact too
        return error
    return None
