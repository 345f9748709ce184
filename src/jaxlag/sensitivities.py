r"""Reverse-mode derivatives of a simulation computed by forward sensitivities.

For a loss of a trajectory in a few parameters θ (k scalars) forward-mode differentiation costs
about ``1 + 0.4 k`` forward passes, while diffrax's checkpointed reverse mode costs 6–8 (measured
in ``benchmarks/``). :class:`ForwardSensitivities`, passed as ``adjoint=`` to
:func:`~jaxlag.simulate`, gives ``jax.grad``/``jax.vjp`` that price:

* on the forward pass of a reverse-mode derivative (``custom_vjp`` with symbolic zeros), the
  simulation is pushed forward (``jax.jvp``, diffrax's ``ForwardMode``) along the k unit
  directions of the inputs that are actually differentiated — the "perturbed" ones: ``args``
  leaves, ``q0``, ``qd0``, times — all k at once under ``jax.vmap``; the sensitivities
  ``S = ∂(outputs)/∂θ`` (k per output entry) are kept;
* the backward pass is one contraction, ``θ̄ = Sᵀ ȳ``.

Memory is k times the saved outputs (not the solver's steps). Inputs that are not differentiated
cost nothing, so ``jax.grad(loss)(g)`` with fixed initial states has k = 1.

Limits: first-order reverse mode only (``jax.grad``, ``jax.vjp``, ``jax.value_and_grad``, also
under ``jit``/``vmap``). For ``jax.jacfwd``/``jax.jvp`` pass ``diffrax.ForwardMode()`` instead
(a ``custom_vjp`` cannot be pushed forward). With many differentiated inputs (a long vector of
parameters) the default ``RecursiveCheckpointAdjoint`` is cheaper: its cost does not grow with k.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jax.custom_derivatives import SymbolicZero


class ForwardSensitivities(eqx.Module):
    """``adjoint=`` for :func:`~jaxlag.simulate`: ``jax.grad`` by forward sensitivities.

    Cheaper than the default checkpointed adjoint when few inputs are differentiated (k ≲ 10);
    see :mod:`jaxlag.sensitivities`. ``inner`` is the diffrax adjoint used to push the
    simulation forward (``diffrax.ForwardMode()``). Differentiating more than ``max_tangents``
    scalars at once (the weights of a neural Lagrangian, say) raises an error that points to the
    default adjoint, instead of building a ``k × k`` basis.
    """

    inner: diffrax.AbstractAdjoint = diffrax.ForwardMode()
    max_tangents: int = eqx.field(static=True, default=256)


def _is_symbolic_zero(x) -> bool:
    return isinstance(x, SymbolicZero)


def _inexact_cotangent(x) -> bool:
    if _is_symbolic_zero(x):
        return jnp.issubdtype(x.aval.dtype, jnp.inexact)
    return eqx.is_inexact_array(x)


def _split_inexact(tree):
    return eqx.partition(tree, eqx.is_inexact_array)


def call_with_forward_sensitivities(run: Callable[[Any], Any], inputs: Any,
                                    max_tangents: int = 256) -> Any:
    """``run(inputs)``, whose reverse-mode derivative is computed from forward sensitivities.

    ``inputs`` is any pytree; its floating-point array leaves are the differentiable inputs.
    ``run`` must be differentiable in forward mode (``jax.jvp``).
    """
    dynamic, static = _split_inexact(inputs)

    def evaluate(values):
        out = run(eqx.combine(values, static))
        inexact, rest = _split_inexact(out)
        return inexact, rest

    shapes = [(jnp.shape(x), jnp.result_type(x)) for x in jax.tree.leaves(dynamic)]
    structure = jax.tree.structure(dynamic)
    # Which leaves are differentiated is known while tracing the forward pass; the backward
    # pass of the same trace reads it here (residuals must be arrays).
    perturbed_sizes: list[int] = []

    @jax.custom_vjp
    def call(values):
        inexact, rest = evaluate(values)
        return eqx.combine(inexact, rest)

    def forward(values):
        leaves = jax.tree.leaves(values, is_leaf=lambda x: hasattr(x, "perturbed"))
        primals = jax.tree.unflatten(structure, [leaf.value for leaf in leaves])
        sizes = [math.prod(shape) if leaf.perturbed else 0
                 for leaf, (shape, _) in zip(leaves, shapes)]
        perturbed_sizes[:] = sizes
        k = sum(sizes)
        if k > max_tangents:
            raise ValueError(
                f"jl.ForwardSensitivities: {k} differentiated scalars would each need a tangent "
                f"(limit max_tangents={max_tangents}). For many parameters use the default "
                "adjoint (diffrax.RecursiveCheckpointAdjoint), whose cost does not grow with "
                "their number."
            )
        if k == 0:
            inexact, rest = evaluate(primals)
            return eqx.combine(inexact, rest), None

        def push(direction):
            tangents, offset = [], 0
            for (shape, dtype), size in zip(shapes, sizes):
                if size:
                    tangents.append(direction[offset:offset + size].reshape(shape).astype(dtype))
                    offset += size
                else:
                    tangents.append(jnp.zeros(shape, dtype))
            return jax.jvp(evaluate, (primals,), (jax.tree.unflatten(structure, tangents),),
                           has_aux=True)

        dtype = jnp.result_type(*[d for (_, d), size in zip(shapes, sizes) if size])
        inexact, sensitivities, rest = jax.vmap(push, out_axes=(None, 0, None))(
            jnp.eye(k, dtype=dtype)
        )
        return eqx.combine(inexact, rest), sensitivities

    def backward(sensitivities, cotangent):
        sizes = perturbed_sizes
        if sensitivities is None:
            return (jax.tree.unflatten(structure, [jnp.zeros(sh, dt) for sh, dt in shapes]),)
        # Cotangents of the inexact outputs, in the order of the sensitivities' leaves (integer
        # outputs have float0 cotangents, symbolic or not, and are skipped).
        cotangents = [c for c in jax.tree.leaves(cotangent, is_leaf=_is_symbolic_zero)
                      if _inexact_cotangent(c)]
        total = None
        for s, c in zip(jax.tree.leaves(sensitivities), cotangents, strict=True):
            if _is_symbolic_zero(c):
                continue
            term = jnp.tensordot(s, c.astype(s.dtype), axes=c.ndim)
            total = term if total is None else total + term
        grads, offset = [], 0
        for (shape, dtype), size in zip(shapes, sizes):
            if size and total is not None:
                grads.append(total[offset:offset + size].reshape(shape).astype(dtype))
            else:
                grads.append(jnp.zeros(shape, dtype))
            offset += size
        return (jax.tree.unflatten(structure, grads),)

    call.defvjp(forward, backward, symbolic_zeros=True)
    return call(dynamic)
