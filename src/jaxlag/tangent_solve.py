r"""One solver loop for a state and its forward sensitivities along k directions.

``jax.vmap(jax.jvp(diffeqsolve))`` differentiates diffrax's whole loop: the JVP rule and then the
batching rule of every operation of the loop machinery (step-size control, interpolation, saving,
the ``while`` carries batched to a fixed point) are traced, and XLA compiles the batched tangent
copy of all of it. Only the solver *step* carries derivative information, though: diffrax does not
differentiate through its step-size choice (the step sizes are the primal run's, a ``stop_gradient``
inside diffrax's loop; verified: a controller with its inputs stopped gives bit-identical
gradients), so the derivative of the discrete solution along a direction ``δ`` is the discrete
solution of the *stepped* tangent recursion

    yₙ₊₁ = Φ(yₙ, θ; tₙ, tₙ₊₁),      Yₙ₊₁ = ∂Φ/∂y · Yₙ + ∂Φ/∂θ · δ,

with ``Φ`` the solver step (including whatever it wraps, e.g. jaxlag's projection onto the
constraint manifold) and the same ``tₙ``. This module runs that recursion inside one ordinary
``diffrax.diffeqsolve`` of the augmented state ``(y, Y)``, ``Y`` holding k tangents:

* :class:`TangentSolver` wraps the solver: its step is ``jax.jvp`` of the wrapped step along the
  k directions (``jax.vmap`` over the tangents only: the primal is computed once), and it
  carries the tangents of the solver state (first-same-as-last stages) and of the dense output;
* :class:`PrimalStepSizes` wraps the step-size controller so that it sees the primal state and
  error estimate only: the steps are exactly those of the primal run;
* :func:`tangent_interpolation` evaluates the primal interpolant and its tangents at save times.

The parameters ``θ`` enter the step through ``args``, the term and the solver's own array
fields (a projected solver holds the system); their tangents along the k directions are fields
of :class:`TangentSolver` (k leading). Times are not differentiated here.

Explicit solvers only (an implicit step's root find is differentiable, but diffrax fills in
its tolerances from the controller only for a solver it recognises as implicit).
"""

from __future__ import annotations

import functools as ft
from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp


def partition_inexact(tree):
    """``eqx.partition`` into inexact arrays (differentiated) and the rest."""
    return eqx.partition(tree, eqx.is_inexact_array)


def push(fn, primals, tangents, in_axes=0):
    """``fn(*primals)`` and its derivatives along k directions: ``(out, tangents_out, aux)``.

    ``fn`` returns ``(differentiable, aux)`` (``aux`` any pytree, e.g. the static half of an
    ``eqx.partition``); ``tangents`` matches ``primals`` (inexact leaves) with a leading k axis
    where ``in_axes`` says 0 (``None``: the same tangent for all k). The primal and ``aux`` are
    computed once (unbatched), the tangents under ``jax.vmap``."""
    held = {}

    def arrays_only(*args):
        out, aux = fn(*args)
        arrays, held["static"] = eqx.partition(aux, eqx.is_array)
        return out, arrays

    def one(tangent):
        return jax.jvp(arrays_only, primals, tangent, has_aux=True)

    out, tangents_out, arrays = jax.vmap(one, in_axes=(in_axes,), out_axes=(None, 0, None))(
        tangents)
    return out, tangents_out, eqx.combine(arrays, held["static"])


def tangent_interpolation(t0, t1, primal, tangent, inner_cls):
    """The interpolant of the augmented state: ``inner_cls`` on the primal dense information
    and, along each of the k directions, its derivative with respect to that information
    (the step's end points ``t0``, ``t1`` fixed)."""
    return TangentInterpolation(t0=t0, t1=t1, primal=primal, tangent=tangent, inner_cls=inner_cls)


class TangentInterpolation(diffrax.AbstractLocalInterpolation):
    """``evaluate(t) = (y(t), Y(t))``: see :func:`tangent_interpolation`."""

    t0: Any
    t1: Any
    primal: Any
    tangent: Any
    inner_cls: Any = eqx.field(static=True)

    def evaluate(self, t0, t1=None, left=True):
        # Jitted: diffrax's three traces of its loop body (each saving at ts) share one trace.
        return _evaluate_tangents(self, t0, t1, left)


@eqx.filter_jit
def _evaluate_tangents(interpolation, t, t_end, left):
    """:meth:`TangentInterpolation.evaluate`."""
    dynamic, static = partition_inexact(interpolation.primal)

    def value(info):
        interpolant = interpolation.inner_cls(t0=interpolation.t0, t1=interpolation.t1,
                                              **eqx.combine(info, static))
        return interpolant.evaluate(t, t_end, left), None

    y, tangents, _ = push(value, (dynamic,), (interpolation.tangent,))
    return y, tangents


class TangentTerm(diffrax.AbstractTerm):
    """The variational term of ``term``: ``vf(t, (y, Y), args) = (f, ∂f/∂y·Y + ∂f/∂θ·δ)`` along
    k directions, ``term_tangent`` (the derivatives of the inexact leaves of ``term``, k leading,
    structured as ``eqx.partition(term, eqx.is_inexact_array)[0]``) and ``args_tangent``
    (likewise for ``args``) holding ``∂θ·δ``. :class:`TangentSolver` steps it."""

    term: diffrax.AbstractTerm
    term_tangent: Any
    args_tangent: Any

    def vf(self, t, y, args):
        y, tangents_y = y
        term_dyn, term_static = partition_inexact(self.term)
        args_dyn, args_static = partition_inexact(args)

        def field(term_dyn, y, args_dyn):
            term = eqx.combine(term_dyn, term_static)
            return term.vf(t, y, eqx.combine(args_dyn, args_static)), None

        value, tangents, _ = push(field, (term_dyn, y, args_dyn),
                                  (self.term_tangent, tangents_y, self.args_tangent))
        return value, tangents

    def contr(self, t0, t1, **kwargs):
        return self.term.contr(t0, t1, **kwargs)

    def prod(self, vf, control):
        value, tangents = vf
        return (self.term.prod(value, control),
                jax.vmap(lambda v: self.term.prod(v, control))(tangents))


def _unwrap(terms):
    """``(tangent_term, rewrap)``: the :class:`TangentTerm` inside diffrax's direction wrapper
    and how to put another term in its place."""
    if isinstance(terms, TangentTerm):
        return terms, lambda term: term
    inner = getattr(terms, "term", None)
    if isinstance(inner, TangentTerm):
        return inner, lambda term: eqx.tree_at(lambda w: w.term, terms, term)
    raise TypeError(f"TangentSolver steps a TangentTerm; got {type(terms).__name__}.")


class TangentSolver(diffrax.AbstractSolver):
    """The wrapped ``solver`` applied to ``(y, Y)`` of a :class:`TangentTerm`: ``Y`` (k leading)
    are the derivatives of ``y`` along k directions of the parameters, whose derivatives in
    the solver's own array fields are ``solver_tangent`` (structured as
    ``eqx.partition(solver, eqx.is_inexact_array)[0]``, k leading) and in the term and ``args``
    the term's. The error estimate is the primal one (pair it with :class:`PrimalStepSizes`)."""

    solver: diffrax.AbstractSolver
    solver_tangent: Any

    # A TangentTerm, whatever the wrapped solver takes inside it. (diffrax checks a structure
    # with vector-field types by evaluating the vector field once: for the variational term a
    # push of the equations of motion, traced for nothing but that check.)
    term_structure = TangentTerm

    @property
    def term_compatible_contr_kwargs(self):
        return self.solver.term_compatible_contr_kwargs

    @property
    def interpolation_cls(self):  # pyright: ignore
        return ft.partial(tangent_interpolation, inner_cls=self.solver.interpolation_cls)

    def order(self, terms):
        return self.solver.order(terms)

    def strong_order(self, terms):
        return self.solver.strong_order(terms)

    def error_order(self, terms):
        return self.solver.error_order(terms)

    def _tangents_of(self, terms, args):
        """The parameters' primal pieces and tangents: ``(primals, tangents, rebuild)``."""
        tangent_term, rewrap = _unwrap(terms)
        term_dyn, term_static = partition_inexact(tangent_term.term)
        solver_dyn, solver_static = partition_inexact(self.solver)
        args_dyn, args_static = partition_inexact(args)

        def rebuild(term_values, solver_values, args_values):
            return (rewrap(eqx.combine(term_values, term_static)),
                    eqx.combine(solver_values, solver_static),
                    eqx.combine(args_values, args_static))

        return ((term_dyn, solver_dyn, args_dyn),
                (tangent_term.term_tangent, self.solver_tangent, tangent_term.args_tangent),
                rebuild)

    def init(self, terms, t0, t1, y0, args):
        y, tangents_y = y0
        (params, param_tangents, rebuild) = self._tangents_of(terms, args)

        def initial(params, y):
            term, solver, args_ = rebuild(*params)
            state = solver.init(term, t0, t1, y, args_)
            dynamic, static = partition_inexact(state)
            return dynamic, static

        state, state_tangent, static = push(initial, (params, y), (param_tangents, tangents_y))
        return eqx.combine(state, static), state_tangent

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # diffrax traces its loop body three times (twice to find which of its state is
        # static); jitted, the derivative of the step is traced once and then served from
        # JAX's tracing cache.
        return _tangent_step(self, terms, t0, t1, y0, args, solver_state, made_jump)

    def primal_func(self, terms, t0, y0, args):
        """The wrapped solver's ``func`` of the primal term and state (the step-size start)."""
        tangent_term, rewrap = _unwrap(terms)
        return self.solver.func(rewrap(tangent_term.term), t0, y0, args)

    def func(self, terms, t0, y0, args):
        y, tangents_y = y0
        (params, param_tangents, rebuild) = self._tangents_of(terms, args)

        def field(params, y):
            term, solver, args_ = rebuild(*params)
            return solver.func(term, t0, y, args_), None

        value, tangents, _ = push(field, (params, y), (param_tangents, tangents_y))
        return value, tangents


@eqx.filter_jit
def _tangent_step(stepper, terms, t0, t1, y0, args, solver_state, made_jump):
    """:meth:`TangentSolver.step`: the wrapped step and its k derivatives (``push``)."""
    y, tangents_y = y0
    state, state_tangent = solver_state
    state_dyn, state_static = partition_inexact(state)
    (params, param_tangents, rebuild) = stepper._tangents_of(terms, args)

    def stepped(params, y, state_dyn):
        term, solver, args_ = rebuild(*params)
        y1, y_error, dense_info, new_state, result = solver.step(
            term, t0, t1, y, args_, eqx.combine(state_dyn, state_static), made_jump)
        info_dyn, info_static = partition_inexact(dense_info)
        new_dyn, new_static = partition_inexact(new_state)
        return (y1, info_dyn, new_dyn), (y_error, info_static, new_static, result)

    (y1, info, new_state), tangents, aux = push(
        stepped, (params, y, state_dyn), (param_tangents, tangents_y, state_tangent))
    tangent_y1, tangent_info, tangent_state = tangents
    y_error, info_static, new_static, result = aux
    dense_info = dict(primal=eqx.combine(info, info_static), tangent=tangent_info)
    return ((y1, tangent_y1), (y_error, None), dense_info,
            (eqx.combine(new_state, new_static), tangent_state), result)


def _primal_func(func, zeros):
    def primal(terms, t, y, args):
        return func(terms, t, (y, zeros), args)[0]

    return primal


def _primal_error(y_error):
    return None if y_error is None else y_error[0]


class PrimalStepSizes(diffrax.AbstractStepSizeController):
    """A (non-adaptive) step-size controller applied to the primal part of ``(y, Y)``."""

    controller: diffrax.AbstractStepSizeController

    def wrap(self, direction):
        return type(self)(self.controller.wrap(direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        owner = getattr(func, "__self__", None)
        if isinstance(owner, TangentSolver):  # no tangents traced for the initial step size
            primal = owner.primal_func
        else:
            primal = _primal_func(func, jax.tree.map(jnp.zeros_like, y0[1]))
        return self.controller.init(terms, t0, t1, y0[0], dt0, args, primal, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order,
                        controller_state):
        return self.controller.adapt_step_size(t0, t1, y0[0], y1_candidate[0], args,
                                               _primal_error(y_error), error_order,
                                               controller_state)


class PrimalAdaptiveStepSizes(diffrax.AbstractAdaptiveStepSizeController):
    """An adaptive step-size controller applied to the primal part of ``(y, Y)``: the same steps
    as the primal run (the tangents take no part in the error norm)."""

    controller: diffrax.AbstractAdaptiveStepSizeController

    @property
    def rtol(self):
        return self.controller.rtol

    @property
    def atol(self):
        return self.controller.atol

    @property
    def norm(self):  # pyright: ignore
        return self.controller.norm

    wrap = PrimalStepSizes.wrap
    init = PrimalStepSizes.init
    adapt_step_size = PrimalStepSizes.adapt_step_size


def primal_step_sizes(controller):
    """``controller`` restricted to the primal state (see :class:`PrimalAdaptiveStepSizes`)."""
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return PrimalAdaptiveStepSizes(controller)
    return PrimalStepSizes(controller)
