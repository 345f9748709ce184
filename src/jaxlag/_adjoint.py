r"""Reverse-mode derivatives of a simulation: forward sensitivities where they pay.

For a loss of a trajectory in a few parameters θ (k scalars) forward-mode differentiation costs
about ``1 + 0.43 k`` forward passes, while diffrax's checkpointed reverse mode costs 5.5–7.5
whatever k is (measured in ``benchmarks/``). `ForwardSensitivities`, the default adjoint of
[`simulate`][jaxlag.simulate], makes ``jax.grad``/``jax.vjp`` pick the cheaper one while tracing:

* the simulation is a ``custom_vjp`` with symbolic zeros, so its forward rule knows which inputs
  are actually differentiated (``args`` leaves, ``q0``, ``qd0``, times: the "perturbed" ones)
  and how many scalars k they hold;
* k ≤ ``max_tangents`` (and the sensitivities fit in ``max_bytes``): the simulation is pushed
  forward along the k unit directions at once: by ``run.push_along`` when the run offers it
  (``simulate``'s one-loop tangent solve, `jaxlag._solver.tangent_solve`), else ``jax.jvp``
  through diffrax's ``ForwardMode`` under ``jax.vmap``; the sensitivities
  ``S = ∂(outputs)/∂θ`` are kept and the backward pass is one contraction ``θ̄ = Sᵀȳ``.
  Memory: k times the saved outputs, not the solver's steps;
* otherwise the ordinary reverse pass of the ``fallback`` adjoint (diffrax's
  ``RecursiveCheckpointAdjoint``) is recorded and replayed.

Both differentiate the same discrete solver, so the gradients agree to rounding (≤ 5e-13
relative measured). A user function that closes over a value being differentiated (``L``
capturing ``g`` from the caller's ``jax.grad``) is invisible to a ``custom_vjp``; ``simulate``
detects traced constants in the jaxpr of the simulation and then differentiates with the
``fallback`` adjoint directly (pass such parameters through ``args`` to get the fast path).

Like the checkpointed adjoint it replaces, this is first-order reverse mode (``jax.grad``,
``jax.vjp``, ``jax.value_and_grad``, under ``jit``/``vmap``); for ``jax.jacfwd`` or ``jax.jvp``
pass ``adjoint=diffrax.ForwardMode()``.
"""

import abc
import math
from collections.abc import Callable
from typing import Any, cast

import diffrax
import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
import numpy as np
from jax.custom_derivatives import SymbolicZero

from . import _compile as compilation
from ._misc import is_concrete


class ForwardSensitivities(eqx.Module):
    """Default ``adjoint=`` of [`simulate`][jaxlag.simulate]: forward sensitivities for few inputs.

    ``jax.grad`` uses forward sensitivities when at most ``max_tangents`` scalars are
    differentiated and ``k ×`` (the saved outputs) is at most ``max_bytes``; otherwise the
    ``fallback`` adjoint's reverse pass. ``inner`` pushes the tangents (``diffrax.ForwardMode()``).
    The default ``max_tangents = 10`` is the measured crossover (k ≈ 11–14 for a double pendulum).
    How it chooses, and what each path costs: [Differentiation modes][differentiation-modes].
    """

    max_tangents: int = eqx.field(static=True, default=10)
    max_bytes: int = eqx.field(static=True, default=2**27)
    inner: diffrax.AbstractAdjoint = diffrax.ForwardMode()
    fallback: diffrax.AbstractAdjoint = diffrax.RecursiveCheckpointAdjoint()


def _is_symbolic_zero(x) -> bool:
    return isinstance(x, SymbolicZero)


def _inexact_cotangent(x) -> bool:
    if _is_symbolic_zero(x):
        return jnp.issubdtype(x.aval.dtype, jnp.inexact)
    return eqx.is_inexact_array(x)


def _split_inexact(tree):
    return eqx.partition(tree, eqx.is_inexact_array)


def _split_static(tree, box: dict):
    """``tree`` without its non-array leaves (an ``eqx.nn.MLP``'s activation function in
    ``args``, the system's functions), which are recorded in ``box["static"]``: what JAX
    transformations return must be arrays, so these leaves go around them, known at trace time."""
    arrays, static = eqx.partition(tree, eqx.is_array)
    box["static"] = static
    return arrays


def _is_inexact_leaf(x) -> bool:
    return jnp.issubdtype(x.dtype, jnp.inexact)


def trace_outputs(run: Callable[[Any, Any], Any], inputs: Any, adjoint) -> tuple[bool, Any]:
    """``(closes_over, shapes)``: whether ``run(inputs, adjoint)`` captures traced values other
    than its inputs, and the shapes of its outputs (``jax.ShapeDtypeStruct`` leaves).

    ``run`` is traced abstractly once (``jax.make_jaxpr``, the inputs' arrays replaced by their
    shapes) and the constants of the jaxpr are inspected: a closed-over parameter of an enclosing
    ``grad``/``jit``/``vmap`` shows up there as a tracer. The same trace gives the output shapes
    the forward rule of `call_with_forward_sensitivities` needs, and fills JAX's tracing
    cache of the jitted solver that the forward rule traces again. Anything that prevents the
    analysis counts as "yes" (the caller then takes the general path).
    """
    dynamic, static = eqx.partition(inputs, eqx.is_array)
    try:
        # Weak types kept: the jitted solver traced here is then found in JAX's tracing cache
        # when the forward rule traces it with the actual inputs.
        spec = jax.tree.map(
            lambda x: jax.ShapeDtypeStruct(
                jnp.shape(x), jnp.result_type(x), weak_type=jax.typeof(x).weak_type
            ),
            dynamic,
        )
        # Array outputs only: non-array leaves (functions in args) are no JAX types.
        closed, shapes = jax.make_jaxpr(
            lambda d: eqx.filter(run(eqx.combine(d, static), adjoint), eqx.is_array), return_shape=True
        )(spec)
    except Exception:  # noqa: BLE001 - conservative: the general path is always correct
        return True, None
    return any(isinstance(c, jax.core.Tracer) for c in closed.consts), shapes


def captures_traced_values(probe: Callable[[Any], Any], inputs: Any) -> bool:
    """Whether ``probe(inputs)`` captures traced values other than its inputs: the test of
    `trace_outputs` on a cheaper function (``simulate``: the system's functions evaluated
    once instead of the solver loop), which must call every user function the run calls.
    Anything that prevents the analysis counts as "yes"."""
    dynamic, static = eqx.partition(inputs, eqx.is_array)
    try:
        spec = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)), dynamic)
        closed = jax.make_jaxpr(lambda d: probe(eqx.combine(d, static)))(spec)
    except Exception:  # noqa: BLE001 - conservative: the general path is always correct
        return True
    return any(isinstance(c, jax.core.Tracer) for c in closed.consts)


def _unit_tangents(shapes, sizes, k):
    """The k unit directions, split by input: ``(tangents, axes)`` with one host array of shape
    ``(k, *shape)`` per differentiated input (axis 0) and zeros of the input's shape for the
    others (not batched). Built in NumPy, so that no small device program is compiled."""
    tangents, axes, offset = [], [], 0
    for (shape, dtype), size in zip(shapes, sizes):
        if size:
            block = np.zeros((k, size), np.dtype(dtype))
            block[offset + np.arange(size), np.arange(size)] = 1
            tangents.append(block.reshape((k,) + tuple(shape)))
            axes.append(0)
        else:
            tangents.append(np.zeros(shape, np.dtype(dtype)))
            axes.append(None)
        offset += size
    return tangents, axes


def _contract_values(xp, sensitivities, cotangents, sizes, shapes):
    """``θ̄ = Sᵀȳ``: the gradient of every input from the sensitivities ``S`` (k leading) and the
    cotangents of the outputs (None where symbolically zero), split back into input shapes.
    ``xp``: the array namespace, ``jax.numpy`` inside a program, NumPy on the host."""
    total = None
    for s, c in zip(sensitivities, cotangents, strict=True):
        if c is None:
            continue
        c = c.astype(s.dtype)
        # Outputs the loss ignores (cotangent exactly 0) contribute 0, even where their
        # sensitivities are not finite: the saved states of a run that failed (inf after the
        # failure, a learned mass matrix gone indefinite) must not make 0 · inf = NaN.
        s = xp.where(c[None] == 0, xp.zeros((), s.dtype), s)
        term = xp.tensordot(s, c, axes=c.ndim)
        total = term if total is None else total + term
    grads, offset = [], 0
    for (shape, dtype), size in zip(shapes, sizes):
        if size and total is not None:
            grads.append(total[offset : offset + size].reshape(shape).astype(dtype))
        else:
            grads.append(xp.zeros(shape, dtype))
        offset += size
    return grads


@compilation.filter_jit
def _contract(sensitivities, cotangents, sizes, shapes):
    """`_contract_values` as one program (traced sensitivities or cotangents: a user's jit)."""
    return _contract_values(jnp, sensitivities, cotangents, sizes, shapes)


def _contracted(sensitivities, cotangents, sizes, shapes):
    """`_contract_values` on the host when every value is known there (an eager ``jax.grad``:
    no program of its own for each shape of loss), else `_contract`."""
    if not is_concrete((sensitivities, cotangents)):
        return _contract(sensitivities, cotangents, sizes, shapes)
    host = _contract_values(
        np,
        [np.asarray(s) for s in sensitivities],
        [None if c is None else np.asarray(c) for c in cotangents],
        sizes,
        shapes,
    )
    return [jax.device_put(g) for g in host]  # a transfer (jnp.asarray compiles a program)


@compilation.filter_jit
def _push(run, static, adjoint, primals, tangents, axes, structure):
    """``run`` and its derivatives along the k unit directions: one compiled program
    (``jax.jvp`` under ``jax.vmap``), reused by every call with equal ``run``, static inputs
    and shapes. Inside it the solver's own jitted function is traced as in
    `trace_outputs`, so JAX's tracing cache serves it. Returns ``(outputs, tangents,
    rest, static)``: the non-array leaves of the output (``static``) are returned by
    ``filter_jit``, not by the transformations."""
    box: dict[str, Any] = {}

    def one(tangent_leaves):
        return jax.jvp(
            lambda v: _split_inexact(_split_static(run(eqx.combine(v, static), adjoint), box)),
            (primals,),
            (jax.tree.unflatten(structure, tangent_leaves),),
            has_aux=True,
        )

    if all(np.shape(t)[0] == 1 for t, axis in zip(tangents, axes) if axis is not None):
        # One direction: a plain jvp (a size-1 vmap would batch the whole solver loop, which
        # costs tracing time and buys nothing).
        single = [t[0] if axis is not None else t for t, axis in zip(tangents, axes)]
        primal, tangent, rest = one(single)
        return primal, jax.tree.map(lambda x: x[None], tangent), rest, box["static"]
    primal, tangent, rest = jax.vmap(one, in_axes=(list(axes),), out_axes=(None, 0, None))(tangents)
    return primal, tangent, rest, box["static"]


class AbstractPushingRun(eqx.Module):
    """A run ``run(inputs, adjoint)`` that can compute its own forward sensitivities (e.g.
    ``simulate``'s one-loop tangent solve), which `call_with_forward_sensitivities` would
    otherwise get by ``jax.vmap`` of ``jax.jvp`` of the whole run. Any other callable takes that
    general path."""

    @abc.abstractmethod
    def __call__(self, inputs: Any, adjoint: Any) -> Any:
        """The run's output with this adjoint."""

    @abc.abstractmethod
    def solves_with_tangents(self, inputs: Any, perturbed: list[bool] | None) -> bool:
        """Whether `push_along` applies when the inexact input leaves flagged in
        ``perturbed`` (leaf order) are differentiated; ``None``: for some perturbed inputs."""

    @abc.abstractmethod
    def push_along(self, primals: Any, static: Any, tangents: Any, axes: tuple, structure: Any) -> Any:
        """``(outputs, tangents, rest)`` along k directions: the outputs' inexact leaves, their k
        tangents (leading axis) and the other leaves."""


def _pushes_itself(run, inputs, sizes) -> bool:
    """Whether ``run`` computes its own forward sensitivities for these perturbed inputs."""
    return isinstance(run, AbstractPushingRun) and run.solves_with_tangents(
        inputs, [size > 0 for size in sizes]
    )


def call_with_forward_sensitivities(
    run: Callable[[Any, Any], Any],
    inputs: Any,
    choice: ForwardSensitivities,
    output_shapes: Any = None,
    finish: Callable[[Any], Any] | None = None,
    prepare: Callable[[Any], Any] | None = None,
    check_residuals: Callable[[Any, Any], Any] | None = None,
) -> Any:
    """``run(inputs, adjoint)``, reverse-differentiated as `ForwardSensitivities` says.

    ``inputs`` is any pytree; its floating-point array leaves are the differentiable inputs.
    ``run(inputs, choice.inner)`` must be differentiable in forward mode (it also computes the
    undifferentiated values) and ``run(inputs, choice.fallback)`` in reverse mode.
    ``output_shapes``: the output shapes of ``run`` if known (`trace_outputs`; saves a
    trace). ``finish``: applied to the primal output (where its values are concrete when the
    caller is not being traced: ``simulate`` raises its failures there, on the host); it must not
    change the values. ``prepare``: applied to the (undifferentiated) inputs before ``run``, in
    the same place (``simulate`` checks the initial state there, on the host when the values are
    concrete, so that the pushed program carries no check); it must not change the values.
    ``check_residuals(output, residuals)``: the residuals of the reverse pass, checked as
    ``finish`` checks the output. A program that uses only the gradient (``jax.jit(jax.grad(…))``
    of an event time) reads no primal output, and would drop the output's compiled check as
    dead code; the backward pass reads the residuals, so their check stays.
    """
    dynamic, static = _split_inexact(inputs)
    shapes = [(jnp.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(dynamic)]
    structure = jax.tree.structure(dynamic)
    finish = finish or (lambda output: output)
    prepare = prepare or (lambda full: full)
    # What the forward rule decided while tracing, read by the backward rule of the same trace
    # (residuals must be arrays): the size of each perturbed leaf, the output structure.
    decided: dict[str, Any] = {}
    # The output's non-array leaves (the system's functions, an eqx.nn.MLP's activation in
    # args), recorded by every Python evaluation below: they go around the custom_vjp and the
    # transformations inside it, which return arrays only.
    box: dict[str, Any] = {}

    def evaluate(values, adjoint):
        return _split_inexact(_split_static(run(eqx.combine(values, static), adjoint), box))

    def prepared(values):
        return _split_inexact(prepare(eqx.combine(values, static)))[0]

    def finished(inexact, rest):
        return _split_inexact(_split_static(finish(eqx.combine(inexact, rest, box["static"])), box))

    @jax.custom_vjp
    def call(values):
        # Not differentiated here (the rules below are): the primal runs with the inner adjoint,
        # whose trace trace_outputs and the forward rule share (an adjoint changes no value).
        inexact, rest = finished(*evaluate(prepared(values), choice.inner))
        return eqx.combine(inexact, rest)

    def forward(values):
        leaves = jax.tree.leaves(values, is_leaf=lambda x: hasattr(x, "perturbed"))
        # Primals of Python scalars arrive as JAX's typed scalars, which jit would treat as
        # static (hashed) values: as arrays (weak type kept) they reuse the compiled program.
        primals = jax.tree.unflatten(
            structure,
            [
                leaf.value if isinstance(leaf.value, (jax.Array, np.ndarray)) else jnp.asarray(leaf.value)
                for leaf in leaves
            ],
        )
        primals = prepared(primals)
        sizes = [math.prod(shape) if leaf.perturbed else 0 for leaf, (shape, _) in zip(leaves, shapes)]
        k = sum(sizes)
        if 0 < k <= choice.max_tangents and _pushes_itself(run, inputs, sizes):
            # One solver loop for the state and its k tangents (jaxlag._solver.tangent_solve), not the
            # jvp and vmap of the whole loop. Its shapes come from a trace that the call reuses.
            tangents, axes = _unit_tangents(shapes, sizes, k)

            def pushed(p, t):
                inexact, tangent, rest = cast(AbstractPushingRun, run).push_along(
                    p, static, t, tuple(axes), structure
                )
                return inexact, tangent, _split_static(rest, box)

            out_shape = jax.eval_shape(pushed, primals, tangents)[0]
            out_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(out_shape))
            if k * out_bytes <= choice.max_bytes:
                decided.update(sizes=sizes, outputs=jax.tree.structure(out_shape))
                inexact, sensitivities, rest = pushed(primals, tangents)
                inexact, rest = finished(inexact, rest)
                return eqx.combine(inexact, rest), (sensitivities, None)
        if output_shapes is None:
            out_shape, _ = jax.eval_shape(lambda v: evaluate(v, choice.inner), primals)
        else:
            out_shape, _ = eqx.partition(output_shapes, _is_inexact_leaf)
        out_bytes = sum(x.size * x.dtype.itemsize for x in jax.tree.leaves(out_shape))
        decided.update(sizes=sizes, outputs=jax.tree.structure(out_shape))
        if k == 0:
            inexact, rest = finished(*evaluate(primals, choice.inner))
            return eqx.combine(inexact, rest), (None, None)
        if k > choice.max_tangents or k * out_bytes > choice.max_bytes:
            inexact, pullback, rest = jax.vjp(lambda v: evaluate(v, choice.fallback), primals, has_aux=True)
            inexact, rest = finished(inexact, rest)
            return eqx.combine(inexact, rest), (None, pullback)

        tangents, axes = _unit_tangents(shapes, sizes, k)
        inexact, sensitivities, rest, box["static"] = _push(
            run, static, choice.inner, primals, tangents, tuple(axes), structure
        )
        inexact, rest = finished(inexact, rest)
        return eqx.combine(inexact, rest), (sensitivities, None)

    def backward(residuals, cotangent):
        sensitivities, pullback = residuals
        # Cotangents of the floating-point outputs in output order (integer outputs have float0
        # cotangents, symbolic or not, and are skipped).
        cotangents = [
            c for c in jax.tree.leaves(cotangent, is_leaf=_is_symbolic_zero) if _inexact_cotangent(c)
        ]
        if pullback is not None:
            dense = [jnp.zeros(c.aval.shape, c.aval.dtype) if _is_symbolic_zero(c) else c for c in cotangents]
            (grads,) = pullback(jax.tree.unflatten(decided["outputs"], dense))
            # A run the loss ignores entirely (every cotangent exactly 0: a failed member masked
            # out of a batch) has gradient 0: the pullback is linear, but its rejected non-finite
            # steps would give 0 · NaN = NaN and poison the other members' sum.
            ignored = jnp.asarray(True)
            for c in cotangents:
                if not _is_symbolic_zero(c):
                    ignored = ignored & jnp.all(c == 0)
            grads = jax.tree.map(lambda g: jnp.where(ignored, jnp.zeros((), g.dtype), g), grads)
            return (grads,)
        if sensitivities is None:
            grads = [jnp.zeros(shape, dtype) for shape, dtype in shapes]
        else:
            grads = _contracted(
                jax.tree.leaves(sensitivities),
                [None if _is_symbolic_zero(c) else c for c in cotangents],
                tuple(decided["sizes"]),
                tuple(shapes),
            )
        return (jax.tree.unflatten(structure, grads),)

    def checked_forward(values):
        output, residuals = forward(values)
        if check_residuals is None or not jax.tree.leaves(residuals):
            return output, residuals
        arrays, static_residuals = eqx.partition(residuals, eqx.is_array)
        full = eqx.combine(output, box.get("static"))
        return output, eqx.combine(check_residuals(full, arrays), static_residuals)

    call.defvjp(checked_forward, backward, symbolic_zeros=True)
    return eqx.combine(call(dynamic), box["static"])
