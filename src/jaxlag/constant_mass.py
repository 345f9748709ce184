r"""Mass matrices that do not depend on the state: found at trace time, inverted once.

For particles and rigid bodies in Cartesian coordinates ``M = ∂²L/∂q̇²`` is a constant. Forming it
by n forward-mode products and factoring it at every evaluation of the right-hand side is then
wasted work. Before integrating, :func:`with_constant_mass` traces ``M(q, q̇, t, args)`` to a jaxpr
(``jax.make_jaxpr``) and follows the data dependencies from its inputs to its output:

* ``M`` depends on none of ``q``, ``q̇``, ``t``, the arrays in ``args`` or any traced value the
  Lagrangian closes over: it is evaluated once while tracing (``jax.ensure_compile_time_eval``)
  and inverted in NumPy. A diagonal ``M`` (checked exactly, on the value) becomes a vector of
  reciprocals, so ``M⁻¹x`` is one multiplication, as with ``System(diagonal_mass=True)``.
* ``M`` depends on ``args`` (masses being fitted, say) but not on the state: it is formed and
  inverted once per integration, outside the solver loop, and stays differentiable in ``args``.
* otherwise (``M(q)`` of generalized coordinates) nothing changes.

The analysis is conservative. An operation's outputs are taken to depend on all of its inputs,
except for calls whose body is followed (``jit``-ted functions, custom derivatives, checkpoints):
a false "depends" only loses the speed-up, it never changes a result.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.extend import core as jex_core

from .linalg import solve_spd
from .mechanics import mass_matrix

#: Primitives whose single sub-jaxpr has the same inputs and outputs as the equation itself, so
#: dependencies can be followed through the body. Loops (``scan``, ``while``) and ``cond`` are
#: not in this list: their outputs are conservatively taken to depend on every input.
_CALL_PRIMITIVES = frozenset({
    "pjit", "jit", "closed_call", "core_call", "custom_jvp_call", "custom_vjp_call",
    "custom_vjp_call_jaxpr", "checkpoint", "remat", "remat2",
})


class ConstantMass(eqx.Module):
    """A state-independent mass matrix with its inverse, computed once.

    Exactly one of ``inverse`` (n, n) and ``inverse_diagonal`` (n,) is set; which one is decided
    while tracing, so the choice costs nothing at run time.
    """

    matrix: Any
    inverse: Any = None
    inverse_diagonal: Any = None

    def solve(self, b):
        """``M⁻¹ b`` for ``b`` of shape (n,) or (n, k)."""
        if self.inverse_diagonal is not None:
            scale = self.inverse_diagonal if b.ndim == 1 else self.inverse_diagonal[:, None]
            return scale * b
        return self.inverse @ b


def _literal(x) -> bool:
    return isinstance(x, jex_core.Literal)


def _output_dependence(jaxpr, input_flags, const_flags):
    """For each output of ``jaxpr``, whether it depends on an input or constant flagged True."""
    depends = {}
    for var, flag in zip(jaxpr.constvars, const_flags):
        depends[var] = flag
    for var, flag in zip(jaxpr.invars, input_flags):
        depends[var] = flag

    def flag_of(var):
        return False if _literal(var) else depends.get(var, False)

    for eqn in jaxpr.eqns:
        in_flags = [flag_of(v) for v in eqn.invars]
        out_flags = None
        if eqn.primitive.name in _CALL_PRIMITIVES:
            bodies = list(jex_core.jaxprs_in_params(eqn.params))
            if len(bodies) == 1:
                body = bodies[0]
                if len(body.invars) == len(in_flags) and len(body.outvars) == len(eqn.outvars):
                    out_flags = _output_dependence(body, in_flags, [False] * len(body.constvars))
        if out_flags is None:
            out_flags = [any(in_flags)] * len(eqn.outvars)
        for var, flag in zip(eqn.outvars, out_flags):
            depends[var] = flag
    return [flag_of(v) for v in jaxpr.outvars]


def _mass_function(system, static_args):
    """``M(q, q̇, t, array_args)`` with a plain identity basis (kept traceable for the analysis)."""

    def mass(q, qd, t, array_args):
        args = eqx.combine(array_args, static_args)

        def momentum(v):
            return jax.grad(lambda b: system.lagrangian(q, b, t=t, args=args))(v)

        basis = jnp.eye(q.shape[0], dtype=qd.dtype)
        return jax.vmap(lambda e: jax.jvp(momentum, (qd,), (e,))[1])(basis)

    return mass


def mass_dependence(system, q, qd, t, args):
    """``(on_state, on_parameters)``: whether ``M`` may depend on ``(q, q̇, t)`` and on traced
    parameters (the arrays in ``args`` or traced values the user's functions close over)."""
    array_args, static_args = eqx.partition(args, eqx.is_array)
    spec = jax.tree.map(lambda x: jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)),
                        (q, qd, t, array_args))
    closed = jax.make_jaxpr(_mass_function(system, static_args))(*spec)
    num_state = len(jax.tree.leaves(spec[:3]))
    num_inputs = len(closed.jaxpr.invars)
    state_flags = [i < num_state for i in range(num_inputs)]
    parameter_flags = [i >= num_state for i in range(num_inputs)]
    traced_consts = [isinstance(c, jax.core.Tracer) for c in closed.consts]
    no_consts = [False] * len(closed.consts)
    (on_state,) = _output_dependence(closed.jaxpr, state_flags, no_consts)
    (on_parameters,) = _output_dependence(closed.jaxpr, parameter_flags, traced_consts)
    return bool(on_state), bool(on_parameters)


def _concrete_mass(system, q, qd, t, args):
    """``M`` as a NumPy array, evaluated while tracing; ``None`` if that is not possible."""
    array_args, static_args = eqx.partition(args, eqx.is_array)
    dummy = jax.tree.map(lambda x: np.zeros(jnp.shape(x), jnp.result_type(x)),
                         (q, qd, t, array_args))
    try:
        with jax.ensure_compile_time_eval():
            value = _mass_function(system, static_args)(*dummy)
        return np.asarray(value)
    except (jax.errors.ConcretizationTypeError, jax.errors.TracerArrayConversionError,
            jax.errors.UnexpectedTracerError):
        return None


def _constant_from_value(mass: np.ndarray) -> ConstantMass:
    eigenvalues = np.linalg.eigvalsh(0.5 * (mass + mass.T)) if mass.size else np.ones(1)
    if not (np.all(np.isfinite(mass)) and np.allclose(mass, mass.T, rtol=1e-12, atol=0.0)
            and eigenvalues.min() > 1e-12 * np.abs(eigenvalues).max()):
        raise ValueError(
            "The mass matrix M = ∂²L/∂q̇² is singular or not positive definite (it is constant: "
            f"it depends on no coordinate, velocity or parameter; eigenvalues {eigenvalues}). The "
            "Lagrangian is degenerate: every coordinate needs a kinetic term with a positive "
            "coefficient.\nM =\n" + str(mass)
        )
    if np.array_equal(mass, np.diag(np.diagonal(mass))):
        return ConstantMass(matrix=mass, inverse_diagonal=1.0 / np.diagonal(mass))
    inverse = np.linalg.inv(mass)
    return ConstantMass(matrix=mass, inverse=0.5 * (inverse + inverse.T))


def constant_mass(system, q, qd, t, args) -> ConstantMass | None:
    """The state-independent mass matrix of ``system`` inverted once, or ``None`` if ``M`` may
    depend on the state (see the module docstring)."""
    on_state, on_parameters = mass_dependence(system, q, qd, t, args)
    if on_state:
        return None
    if not on_parameters:
        value = _concrete_mass(system, q, qd, t, args)
        if value is not None:
            return _constant_from_value(value)
    mass = mass_matrix(system, q, qd, t, args)
    if system.diagonal_mass:
        return ConstantMass(matrix=mass, inverse_diagonal=1.0 / jnp.diagonal(mass))
    return ConstantMass(matrix=mass, inverse=solve_spd(mass, jnp.eye(q.shape[0], dtype=q.dtype)))


def with_constant_mass(system, q, qd, t, args):
    """``system`` carrying its :class:`ConstantMass` when ``M`` does not depend on the state."""
    if system.constant_mass is not None:
        return system
    found = constant_mass(system, q, qd, t, args)
    if found is None:
        return system
    return eqx.tree_at(lambda s: s.constant_mass, system, found, is_leaf=lambda x: x is None)
