"""Time-table inputs (the implementation of `jaxlag.inputs`, which documents them)."""

import abc
from typing import ClassVar

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree

from . import _compile as compilation
from ._conventions import host_to_jax
from ._custom_types import RealScalarLike, Validated
from ._errors import compiled_check
from ._misc import is_concrete

_TS_MESSAGE = "A time table's `ts` must be finite and strictly increasing (t₀ < t₁ < … < t_{N−1})."
_VALUES_MESSAGE = "A time table's `values` must be finite (no NaN or inf)."


def _as_float_array(x, name: str) -> Array:
    x = host_to_jax(x)
    if jnp.issubdtype(x.dtype, jnp.complexfloating):
        raise TypeError(f"A time table's `{name}` must be real; got dtype {x.dtype}.")
    if not jnp.issubdtype(x.dtype, jnp.floating):
        x = x.astype(jnp.result_type(float))
    return x


def _first_bad_index(values: np.ndarray) -> int:
    bad = ~np.isfinite(values.reshape(values.shape[0], -1)).all(axis=1)
    return int(np.argmax(bad))


class AbstractTimeTable(eqx.Module):
    r"""A time table ``u(t)`` from samples ``ts`` (N,), ``values`` (N, *shape).

    Calling the table, ``table(t)``, gives ``u(t)`` of shape ``shape`` (a scalar for ``values``
    of shape (N,)). Outside ``[ts[0], ts[-1]]`` the end values hold.

    Construction checks the table: ``ts`` one-dimensional, finite and strictly increasing,
    ``values`` with ``values.shape[0] == len(ts)`` and finite. Concrete arrays are checked at once
    (``ValueError`` naming the first bad index); traced ones (a table built inside ``jax.jit``)
    are checked in the compiled program (``eqx.error_if``).
    """

    ts: Float[Array, " N"]
    values: Float[Array, " N *shape"]

    #: whether ``u`` itself jumps at the breakpoints (diffrax ``jump_ts``) or only a derivative does
    #: (``step_ts``).
    discontinuous: ClassVar[bool] = False
    #: the fewest samples the interpolation needs.
    min_samples: ClassVar[int] = 2

    def __init__(
        self, ts: Validated[Float[ArrayLike, " N"]], values: Validated[Float[ArrayLike, " N *shape"]]
    ):
        name = type(self).__name__
        times = _as_float_array(ts, "ts")
        samples = _as_float_array(values, "values")
        if times.ndim != 1:
            raise ValueError(f"{name}: ts must be a 1-D array of sample times; got shape {times.shape}.")
        if times.shape[0] < self.min_samples:
            raise ValueError(
                f"{name}: needs at least {self.min_samples} samples; got ts of shape {times.shape}."
            )
        if samples.ndim < 1 or samples.shape[0] != times.shape[0]:
            raise ValueError(
                f"{name}: values must have one row per sample time, shape ({times.shape[0]}, ...) "
                f"for ts of shape {times.shape}; got values of shape {samples.shape}."
            )
        if is_concrete(times):
            t = np.asarray(times)
            if not np.all(np.isfinite(t)):
                i = int(np.argmax(~np.isfinite(t)))
                raise ValueError(
                    f"{name}: ts[{i}] = {float(t[i])} is not finite; sample times must be finite."
                )
            steps = np.diff(t)
            if np.any(steps <= 0):
                i = int(np.argmax(steps <= 0)) + 1
                raise ValueError(
                    f"{name}: ts must be strictly increasing; ts[{i}] = {float(t[i])} does not exceed "
                    f"ts[{i - 1}] = {float(t[i - 1])}."
                )
        else:
            ok = jnp.all(jnp.isfinite(times)) & jnp.all(jnp.diff(times) > 0)
            times = compiled_check(times, ~ok, 0, (_TS_MESSAGE,))
        if is_concrete(samples):
            v = np.asarray(samples)
            if not np.all(np.isfinite(v)):
                i = _first_bad_index(v)
                raise ValueError(f"{name}: values[{i}] = {v[i]} is not finite; table values must be finite.")
        else:
            samples = compiled_check(samples, ~jnp.all(jnp.isfinite(samples)), 0, (_VALUES_MESSAGE,))
        self.ts = times
        self.values = samples

    @property
    def breakpoints(self) -> Float[Array, " N"]:
        """The sample times, where ``u`` or one of its derivatives is not smooth (no gradient flows
        through them: they only tell the solver where to step)."""
        return jax.lax.stop_gradient(self.ts)

    def _times(self, t: RealScalarLike) -> tuple[Array, Array]:
        """``(ts, t)`` in their common floating dtype (a float64 table may drive a float32
        simulation under strict dtype promotion)."""
        t = jnp.asarray(t)
        dtype = np.promote_types(self.ts.dtype, t.dtype)
        return self.ts.astype(dtype), t.astype(dtype)

    @abc.abstractmethod
    def __call__(self, t: RealScalarLike) -> Float[Array, " *shape"]:
        """``u(t)``, of shape ``values.shape[1:]``."""


class ZeroOrderHold(AbstractTimeTable):
    r"""Zero-order hold: ``u(t) = uᵢ`` for ``tᵢ ≤ t < tᵢ₊₁``, the value of the last sample at or
    before ``t``.

    Right-continuous: at a sample time ``tᵢ`` the new value ``uᵢ`` holds. Before ``t₀`` the table
    gives ``u₀``, after ``t_{N−1}`` it holds ``u_{N−1}``. One sample is allowed (a constant).
    ``u`` jumps at ``t₁, …, t_{N−1}``; [`simulate`][jaxlag.simulate] steps onto them as diffrax
    ``jump_ts``.

    **Arguments:** ``ts`` (N,), strictly increasing; ``values`` (N,) or (N, *shape).

    ``jax.grad`` with respect to ``values`` is exact (``∂u(t)/∂uᵢ`` is 1 on ``[tᵢ, tᵢ₊₁)``); with
    respect to ``ts`` it is zero (the jump times are not differentiated).
    """

    discontinuous: ClassVar[bool] = True
    min_samples: ClassVar[int] = 1

    def __call__(self, t: RealScalarLike) -> Float[Array, " *shape"]:
        return _table_value(self, jnp.asarray(t))

    def _value(self, t: Array) -> Array:
        ts, t = self._times(t)
        index = jnp.searchsorted(ts, t, side="right") - 1
        return self.values[jnp.clip(index, 0, self.ts.shape[0] - 1)]


class PiecewiseLinear(AbstractTimeTable):
    r"""Piecewise-linear interpolation,
    ``u(t) = uᵢ + (uᵢ₊₁ − uᵢ)(t − tᵢ)/(tᵢ₊₁ − tᵢ)`` on ``[tᵢ, tᵢ₊₁]``.

    Continuous, with kinks at the samples (which [`simulate`][jaxlag.simulate] steps onto as diffrax
    ``step_ts``). Holds the end values outside ``[t₀, t_{N−1}]``. Evaluated by
    ``diffrax.LinearInterpolation``.

    **Arguments:** ``ts`` (N,), N ≥ 2, strictly increasing; ``values`` (N,) or (N, *shape).
    """

    def __call__(self, t: RealScalarLike) -> Float[Array, " *shape"]:
        return _table_value(self, jnp.asarray(t))

    def _value(self, t: Array) -> Array:
        ts, t = self._times(t)
        path = diffrax.LinearInterpolation(ts=ts, ys=self.values)
        return path.evaluate(jnp.clip(t, ts[0], ts[-1]))


class CubicSpline(AbstractTimeTable):
    r"""The natural cubic spline through the samples.

    On ``[tᵢ, tᵢ₊₁]``, with ``s = t − tᵢ`` and ``hᵢ = tᵢ₊₁ − tᵢ``,
    ``u(t) = uᵢ + bᵢ s + mᵢ s²/2 + (mᵢ₊₁ − mᵢ) s³/(6hᵢ)``,
    ``bᵢ = (uᵢ₊₁ − uᵢ)/hᵢ − hᵢ(2mᵢ + mᵢ₊₁)/6``, where the second derivatives ``mᵢ = u″(tᵢ)`` solve
    the tridiagonal system
    ``hᵢ₋₁ mᵢ₋₁ + 2(hᵢ₋₁ + hᵢ) mᵢ + hᵢ mᵢ₊₁ = 6[(uᵢ₊₁ − uᵢ)/hᵢ − (uᵢ − uᵢ₋₁)/hᵢ₋₁]``
    with the natural end conditions ``m₀ = m_{N−1} = 0``.

    ``u`` is twice continuously differentiable on ``[t₀, t_{N−1}]`` and interpolates every
    sample; ``u‴`` jumps at the samples ([`simulate`][jaxlag.simulate] steps onto them as diffrax
    ``step_ts``). Outside the table the end values hold (``u`` stays continuous there, ``u′``
    jumps to zero). Two samples give the straight line. The spline is global: each value moves
    the whole curve a little (it is not causal). The system is solved on every call (``O(N)``,
    ``jax.lax.linalg.tridiagonal_solve``), so ``jax.grad`` with respect to ``values`` is exact
    however the table is built or updated; the evaluation is ``diffrax.CubicInterpolation``.

    **Arguments:** ``ts`` (N,), N ≥ 2, strictly increasing; ``values`` (N,) or (N, *shape).
    """

    def coefficients(self) -> tuple[Array, Array, Array, Array]:
        """``(d, c, b, a)`` of each interval, shape (N − 1, *shape), in diffrax's order:
        ``u = a + b s + c s² + d s³``."""
        n = self.ts.shape[0]
        shape = self.values.shape[1:]
        y = self.values.reshape(n, -1)
        h = jnp.diff(self.ts).astype(y.dtype)
        slope = (y[1:] - y[:-1]) / h[:, None]
        if n > 2:
            rhs = 6.0 * (slope[1:] - slope[:-1])
            lower = jnp.concatenate([jnp.zeros((1,), h.dtype), h[1:-1]])
            upper = jnp.concatenate([h[1:-1], jnp.zeros((1,), h.dtype)])
            diagonal = 2.0 * (h[:-1] + h[1:])
            inner = jax.lax.linalg.tridiagonal_solve(lower, diagonal, upper, rhs)
            zero = jnp.zeros((1, y.shape[1]), y.dtype)
            m = jnp.concatenate([zero, inner, zero])
        else:
            m = jnp.zeros_like(y)
        a = y[:-1]
        b = slope - h[:, None] * (2.0 * m[:-1] + m[1:]) / 6.0
        c = m[:-1] / 2.0
        d = (m[1:] - m[:-1]) / (6.0 * h[:, None])
        return tuple(x.reshape((n - 1, *shape)) for x in (d, c, b, a))  # pyright: ignore[reportReturnType]

    def __call__(self, t: RealScalarLike) -> Float[Array, " *shape"]:
        return _table_value(self, jnp.asarray(t))

    def _value(self, t: Array) -> Array:
        ts, t = self._times(t)
        path = diffrax.CubicInterpolation(ts=ts, coeffs=self.coefficients())
        return path.evaluate(jnp.clip(t, ts[0], ts[-1]))


@compilation.filter_jit
def _table_value(table, t):
    """A built-in table's ``u(t)``: one program per table type and shapes when called eagerly (or
    under an eager ``jax.vmap`` over times), instead of one per operation; inlined inside a
    ``jit`` (the equations of motion)."""
    return table._value(t)


def _tables(tree) -> list[AbstractTimeTable]:
    leaves = jax.tree.leaves(tree, is_leaf=lambda x: isinstance(x, AbstractTimeTable))
    return [x for x in leaves if isinstance(x, AbstractTimeTable)]


def with_breakpoints(
    controller: Validated[diffrax.AbstractAdaptiveStepSizeController], *tables: PyTree
) -> diffrax.ClipStepSizeController:
    """``controller`` told to step onto the breakpoints of ``tables``.

    Returns a ``diffrax.ClipStepSizeController`` around ``controller`` whose ``jump_ts`` are
    the sample times of every `ZeroOrderHold` and whose ``step_ts`` are those of the other
    tables. A ``ClipStepSizeController`` given as ``controller`` keeps its own ``step_ts`` and
    ``jump_ts`` (the times are merged). ``tables`` may be tables or pytrees holding tables (an
    ``args`` dict). [`simulate`][jaxlag.simulate] already does this for the tables in its ``args``::

        controller = inputs.with_breakpoints(diffrax.PIDController(rtol=1e-8, atol=1e-8), u)
    """
    found = _tables(tables)
    if not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        raise TypeError(
            "with_breakpoints needs an adaptive step-size controller such as "
            f"diffrax.PIDController(rtol=..., atol=...); got {type(controller).__name__}. A fixed "
            "step does not adapt: choose steps that land on the table's sample times."
        )
    if not found:
        raise ValueError(
            "with_breakpoints was given no time table (jaxlag.inputs.ZeroOrderHold, "
            "PiecewiseLinear or CubicSpline)."
        )
    return _clip(controller, found, None)


@compilation.filter_jit  # one program per shapes (eagerly, each operation would be one)
def _merged_times(times, dtype):
    out = jnp.concatenate([jnp.ravel(x) for x in times])
    return out if dtype is None else out.astype(dtype)


def _clip(controller, tables, dtype):
    jumps = [t.breakpoints for t in tables if t.discontinuous]
    steps = [t.breakpoints for t in tables if not t.discontinuous]
    inner = controller
    if isinstance(controller, diffrax.ClipStepSizeController):
        inner = controller.controller
        if controller.jump_ts is not None:
            jumps.append(controller.jump_ts)
        if controller.step_ts is not None:
            steps.append(controller.step_ts)

    def merge(times):
        return _merged_times(tuple(times), dtype) if times else None

    store, callback = None, None
    if isinstance(controller, diffrax.ClipStepSizeController):
        store, callback = controller.store_rejected_steps, controller.callback_on_reject
    return diffrax.ClipStepSizeController(
        inner,
        step_ts=merge(steps),
        jump_ts=merge(jumps),
        store_rejected_steps=store,
        _callback_on_reject=callback,
    )


def controller_for_args(controller, args, dtype):
    """``simulate``'s controller, told the breakpoints of the time tables in ``args`` (an
    adaptive controller only; a fixed step is returned as it is). The times of a
    ``ClipStepSizeController`` (one from `with_breakpoints`, say) take the time's ``dtype``:
    a float64 table may drive a float32 simulation."""
    if not isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return controller
    tables = _tables(args)
    if not tables and not isinstance(controller, diffrax.ClipStepSizeController):
        return controller
    return _clip(controller, tables, dtype)
