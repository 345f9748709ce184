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

* `TangentTerm` is the variational vector field ``(f, ∂f/∂y·Y + ∂f/∂θ·δ)`` (``jax.jvp``
  of the equations of motion along the k directions, ``jax.vmap`` over the tangents only: the
  primal is computed once). An explicit Runge–Kutta step of it is exactly the ``jvp`` of the
  step of ``f`` (each stage is a vector-field evaluation, the rest is linear in the stages), and
  the solver's dense output, linear in its stages too, interpolates ``Y`` with ``y``;
* `TangentSolver` steps it with the wrapped solver; a projected solver's projection of
  ``y`` after the step is pushed forward along the k tangents (``push``);
* `PrimalStepSizes` wraps the step-size controller so that it sees the primal state and
  error estimate only: the steps are exactly those of the primal run.

The parameters ``θ`` enter through ``args`` and the term's arrays (and the projected solver's
system); their tangents along the k directions are fields of `TangentTerm` and
`TangentSolver` (k leading). Times are not differentiated here. The gradient equals
``jax.vmap(jax.jvp(...))`` of the solve to rounding (≤ 5e-16 relative measured on the README
example; tests compare with diffrax's ``RecursiveCheckpointAdjoint``).

Explicit solvers only (an implicit step's root find is differentiable, but diffrax fills in
its tolerances from the controller only for a solver it recognises as implicit), whose own
arrays are not differentiated.
"""

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp

from .._stabilization import ProjectedSolver
from .forwarding import ForwardingAdaptiveController, ForwardingSolver


def partition_inexact(tree):
    """``eqx.partition`` into inexact arrays (differentiated) and the rest."""
    return eqx.partition(tree, eqx.is_inexact_array)


def push(fn, primals, tangents, in_axes: Any = 0):
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

    out, tangents_out, arrays = jax.vmap(one, in_axes=(in_axes,), out_axes=(None, 0, None))(tangents)
    return out, tangents_out, eqx.combine(arrays, held["static"])


class TangentTerm(diffrax.AbstractTerm):
    """The variational term of ``term``: ``vf(t, (y, Y), args) = (f, ∂f/∂y·Y + ∂f/∂θ·δ)`` along
    k directions, ``term_tangent`` (the derivatives of the inexact leaves of ``term``, k leading,
    structured as ``eqx.partition(term, eqx.is_inexact_array)[0]``) and ``args_tangent``
    (likewise for ``args``) holding ``∂θ·δ``. `TangentSolver` steps it."""

    term: diffrax.AbstractTerm
    term_tangent: Any
    args_tangent: Any

    def vf(self, t, y, args):
        # Jitted: diffrax's term check, the step-size start and every trace of the solver step
        # share one trace of the pushed equations of motion.
        return _variational_field(self, t, y, args)

    def contr(self, t0, t1, **kwargs):
        return self.term.contr(t0, t1, **kwargs)

    def prod(self, vf, control):
        value, tangents = vf
        return (self.term.prod(value, control), jax.vmap(lambda v: self.term.prod(v, control))(tangents))


@eqx.filter_jit
def _variational_field(tangent_term, t, y, args):
    """`TangentTerm.vf`."""
    y, tangents_y = y
    term_dyn, term_static = partition_inexact(tangent_term.term)
    args_dyn, args_static = partition_inexact(args)

    def field(term_dyn, y, args_dyn):
        term = eqx.combine(term_dyn, term_static)
        return term.vf(t, y, eqx.combine(args_dyn, args_static)), None

    value, tangents, _ = push(
        field, (term_dyn, y, args_dyn), (tangent_term.term_tangent, tangents_y, tangent_term.args_tangent)
    )
    return value, tangents


def _unwrap(terms):
    """``(tangent_term, rewrap)``: the `TangentTerm` inside diffrax's direction wrapper
    and how to put another term in its place."""
    if isinstance(terms, TangentTerm):
        return terms, lambda term: term
    inner = getattr(terms, "term", None)
    if isinstance(inner, TangentTerm):
        return inner, lambda term: eqx.tree_at(lambda w: w.term, terms, term)
    raise TypeError(f"TangentSolver steps a TangentTerm; got {type(terms).__name__}.")


class TangentSolver(ForwardingSolver):
    """``solver`` stepping a `TangentTerm` on ``(y, Y)``, ``Y`` (k leading) the
    derivatives of ``y`` along k directions of the parameters.

    An explicit Runge–Kutta step of the variational equations is the ``jvp`` of the step of
    the equations (every stage is a vector-field evaluation and the rest is linear), so the
    wrapped solver steps the augmented state as it is, its dense output interpolates both. A
    `ProjectedSolver` projects ``y`` after the step and pushes
    ``Y`` through the projection (``push``), with the derivatives of its system's arrays,
    ``projection_tangent`` (structured as ``eqx.partition(solver.system, is_inexact)[0]``, k
    leading), and of ``args`` (the term's). The error estimate includes the tangents: pair the
    solver with `PrimalStepSizes`, which looks at the state's only."""

    solver: diffrax.AbstractSolver
    projection_tangent: Any = None

    @property
    def term_structure(self):
        """A TangentTerm, whatever the wrapped solver takes inside it."""
        return TangentTerm

    def step(self, terms, t0, t1, y0, args, solver_state, made_jump):
        # Jitted: diffrax traces its loop body three times, the step is traced once.
        return _tangent_step(self, terms, t0, t1, y0, args, solver_state, made_jump)

    def primal_func(self, terms, t0, y0, args):
        """The wrapped solver's ``func`` of the primal term and state (the step-size start)."""
        tangent_term, rewrap = _unwrap(terms)
        return self.solver.func(rewrap(tangent_term.term), t0, y0, args)


@eqx.filter_jit
def _tangent_step(stepper, terms, t0, t1, y0, args, solver_state, made_jump):
    """`TangentSolver.step`."""
    solver = stepper.solver
    if type(solver) is not ProjectedSolver:
        return solver.step(terms, t0, t1, y0, args, solver_state, made_jump)
    y1, y_error, dense_info, solver_state, result = solver.solver.step(
        terms, t0, t1, y0, args, solver_state, made_jump
    )
    tangent_term, _ = _unwrap(terms)
    system_dyn, system_static = partition_inexact(solver.system)
    args_dyn, args_static = partition_inexact(args)

    def projected(system_dyn, y, args_dyn):
        system = eqx.combine(system_dyn, system_static)
        q, qd = solver.projection(system, y[0], y[1], t1, eqx.combine(args_dyn, args_static), solver.active)
        return (q, qd), None

    y1, tangents, _ = push(
        projected,
        (system_dyn, y1[0], args_dyn),
        (stepper.projection_tangent, y1[1], tangent_term.args_tangent),
    )
    return (y1, tangents), y_error, dense_info, solver_state, result


def _primal_func(func, zeros):
    def primal(terms, t, y, args):
        return func(terms, t, (y, zeros), args)[0]

    return primal


def _primal_start(owner):
    """The `TangentSolver`'s ``primal_func`` as the solver ``owner`` (it or a wrapper around it,
    e.g. SaveTimes) presents its ``func``: no tangents traced for the initial step size. None if
    there is no TangentSolver inside."""
    if type(owner) is TangentSolver:
        return owner.primal_func
    if not isinstance(owner, diffrax.AbstractWrappedSolver):
        return None
    inner = _primal_start(owner.solver)
    # A wrapper that changes the time variable (UnitTimeSolver) says how its func looks outside.
    seen_from_outside = getattr(owner, "seen_from_outside", None)
    return inner if inner is None or seen_from_outside is None else seen_from_outside(inner)


def _primal_error(y_error):
    return None if y_error is None else y_error[0]


class PrimalStepSizes(diffrax.AbstractStepSizeController):
    """A (non-adaptive) step-size controller applied to the primal part of ``(y, Y)``."""

    controller: diffrax.AbstractStepSizeController

    def wrap(self, direction):
        return type(self)(self.controller.wrap(direction))

    def init(self, terms, t0, t1, y0, dt0, args, func, error_order):
        primal = _primal_start(getattr(func, "__self__", None))
        if primal is None:
            primal = _primal_func(func, jax.tree.map(jnp.zeros_like, y0[1]))
        return self.controller.init(terms, t0, t1, y0[0], dt0, args, primal, error_order)

    def adapt_step_size(self, t0, t1, y0, y1_candidate, args, y_error, error_order, controller_state):
        return self.controller.adapt_step_size(
            t0, t1, y0[0], y1_candidate[0], args, _primal_error(y_error), error_order, controller_state
        )


class PrimalAdaptiveStepSizes(ForwardingAdaptiveController):
    """An adaptive step-size controller applied to the primal part of ``(y, Y)``: the same steps
    as the primal run (the tangents take no part in the error norm)."""

    controller: diffrax.AbstractAdaptiveStepSizeController

    wrap = PrimalStepSizes.wrap
    init = PrimalStepSizes.init
    adapt_step_size = PrimalStepSizes.adapt_step_size


def primal_step_sizes(controller):
    """``controller`` restricted to the primal state (see `PrimalAdaptiveStepSizes`)."""
    if isinstance(controller, diffrax.AbstractAdaptiveStepSizeController):
        return PrimalAdaptiveStepSizes(controller)  # pyright: ignore[reportCallIssue]
    return PrimalStepSizes(controller)
