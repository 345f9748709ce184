r"""Mass matrices that do not depend on the state: found at trace time, inverted once.

For particles and rigid bodies in Cartesian coordinates ``M = ∂²L/∂q̇²`` is a constant. Forming it
by n forward-mode products and factoring it at every evaluation of the right-hand side is then
wasted work. Before integrating, `with_constant_mass` traces ``M(q, q̇, t, args)`` to a jaxpr
(``jax.make_jaxpr``) and follows the data dependencies from its inputs to its output:

* ``M`` depends on none of ``q``, ``q̇``, ``t``, the arrays in ``args`` or any traced value the
  Lagrangian closes over: it is evaluated once while tracing (``jax.ensure_compile_time_eval``)
  and inverted in NumPy. A diagonal ``M`` (checked exactly, on the value) becomes a vector of
  reciprocals, so ``M⁻¹x`` is one multiplication, as with ``System(diagonal_mass=True)``.
* ``M`` depends on ``args`` (masses being fitted, say) but not on the state: it is formed and
  inverted once per integration, outside the solver loop, and stays differentiable in ``args``.
* otherwise (``M(q)`` of generalized coordinates) nothing changes.

The analysis (`jaxlag._mechanics.dependence`) is conservative: a false "depends" only loses the
speed-up, it never changes a result.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .. import _compile as compilation
from .._tolerances import MASS_RCOND
from .dependence import may_depend
from .lagrangian import mass_matrix
from .linalg import solve_spd


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


def _mass(q, qd, t, args, system):
    """``M(q, q̇, t)`` from the system's dynamics, written for the analysis (the autodiff hot
    path's basis is built from ``q̇`` so XLA cannot hoist it, which would make every ``M`` look
    velocity-dependent here: `AbstractDynamics.dependence_mass`)."""
    return system.dynamics.dependence_mass(system, q, qd, t, args)


_mass_program = compilation.filter_jit(_mass)


def mass_dependence(system, q, qd, t, args):
    """``(on_state, on_parameters)``: whether ``M`` may depend on ``(q, q̇, t)``, and on traced
    parameters (the arrays in ``args`` or in ``system``, or traced values its functions close
    over)."""
    (on_q, on_qd, on_t, on_args, on_system), on_closure = may_depend(_mass, (q, qd, t, args, system))
    return on_q or on_qd or on_t, on_args or on_system or on_closure


def _concrete_mass(system, q, qd, t, args):
    """``M`` as a NumPy array, evaluated while tracing; ``None`` if that is not possible.

    Only called when ``M`` depends on no input, so the inputs (and the arrays in ``args`` and
    ``system``) are replaced by zeros: nothing traced enters the evaluation except what the
    user's functions close over, on which ``M`` does not depend either.
    """

    def zeros(x):  # other arrays (integers, PRNG keys) are kept: M does not depend on them
        return np.zeros(jnp.shape(x), jnp.result_type(x)) if eqx.is_inexact_array(x) else x

    try:
        inputs = jax.tree.map(zeros, (q, qd, t, args, system))
    except Exception:  # noqa: BLE001 - an optimisation: fall back to inverting M at run time
        return None
    try:
        # One program, traced and compiled on the side (not staged into the program being
        # traced) and run on the zeros: evaluated op by op, every operation of L's Hessian would
        # compile a small program of its own (~20 for a pendulum, 0.4 s in a fresh process).
        return np.asarray(_mass_program.lower(*inputs).compile()(*inputs))
    except Exception:  # noqa: BLE001 - e.g. L closes over a traced value: op by op instead
        pass
    try:
        with jax.ensure_compile_time_eval():
            return np.asarray(_mass(*inputs))
    except Exception:  # noqa: BLE001 - an optimisation: fall back to inverting M at run time
        return None


def _constant_from_value(mass: np.ndarray) -> ConstantMass:
    """Invert a concrete ``M``; raise if it is singular (the Lagrangian is degenerate)."""
    mass = 0.5 * (mass + mass.T)  # a Hessian: symmetric up to rounding
    eigenvalues = np.linalg.eigvalsh(mass) if mass.size else np.ones(1)
    if not (np.all(np.isfinite(mass)) and eigenvalues.min() > MASS_RCOND * np.abs(eigenvalues).max()):
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
    try:
        on_state, on_parameters = mass_dependence(system, q, qd, t, args)
    except Exception:  # noqa: BLE001 - an optimisation: an L it cannot analyse takes the general path
        return None
    if on_state:
        return None
    if not system.mass_solve.checked:
        # A learned constant M (jl.RobustSolve) is judged by its factorization: a failed one
        # gives a NaN inverse with a zero gradient, never NumPy's inverse of an indefinite M.
        mass = mass_matrix(system, q, qd, t, args)
        factor = system.mass_solve.factor(mass, system.diagonal_mass)
        return ConstantMass(matrix=mass, inverse=factor(jnp.eye(q.shape[0], dtype=q.dtype)))
    if not on_parameters:
        value = _concrete_mass(system, q, qd, t, args)
        if value is not None:
            return _constant_from_value(value)
    mass = mass_matrix(system, q, qd, t, args)
    if system.diagonal_mass:
        return ConstantMass(matrix=mass, inverse_diagonal=1.0 / jnp.diagonal(mass))
    return ConstantMass(matrix=mass, inverse=solve_spd(mass, jnp.eye(q.shape[0], dtype=q.dtype)))


def with_constant_mass(system, q, qd, t, args):
    """``system`` carrying its `ConstantMass` when ``M`` does not depend on the state."""
    if system.constant_mass is not None:
        return system
    found = constant_mass(system, q, qd, t, args)
    if found is None:
        return system
    return eqx.tree_at(lambda s: s.constant_mass, system, found, is_leaf=lambda x: x is None)
