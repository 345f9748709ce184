r"""Where ``M`` and ``F`` of the equations of motion come from: a [`System`][jaxlag.System] option.

The equations of motion ``M q̈ = F + Jᵀλ + Aᵀμ`` split ``F`` into the Lagrangian part and the
non-conservative forces,

    F = F_L + Qⁿᶜ,    F_L = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t,    Qⁿᶜ = −∂R/∂q̇ + Q_ext + Q_u.

A dynamics object gives ``M = ∂²L/∂q̇²`` and ``F_L``; the system adds ``Qⁿᶜ`` from its
``dissipation``, ``forces`` and ``actuation`` (so each is counted once, and the power balances
of `jaxlag.analysis` keep using them). `AutodiffDynamics` (the default) differentiates ``L``;
another implementation (e.g. the recursive algorithms of a kinematic tree,
`jaxlag.robots.TreeDynamics`) must compute the same two quantities of the same ``L``:
everything else (momenta, energy, the variational integrator) still comes from ``L`` itself.
"""

import abc

import equinox as eqx
import jax.numpy as jnp
from jaxtyping import Array, ArrayLike, Float

from .._custom_types import Args
from .lagrangian import _unit_basis, _velocity_terms, mass_along
from .mass_solve import Factorization


class AbstractDynamics(eqx.Module):
    r"""The mass matrix and the Lagrangian forces of ``M q̈ = F_L + Qⁿᶜ + Jᵀλ + Aᵀμ``.

    Subclasses implement `mass_matrix` and `forces`, and may override `mass_and_forces` where
    the two share work, and `mass_solver`/`solver_and_forces` to apply ``M⁻¹`` without forming
    ``M`` (every solve of the equations of motion, impacts and projections goes through them).
    Every method takes the [`System`][jaxlag.System] (for its ``L``), the state ``(q, q̇)``
    (n,), the time ``t`` (an array of ``q``'s floating dtype) and ``args``.
    """

    @abc.abstractmethod
    def mass_matrix(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        """``M = ∂²L/∂q̇²``, shape (n, n), symmetric positive definite."""

    @abc.abstractmethod
    def forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, " n"]:
        """``F_L = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t``, shape (n,) (without ``Qⁿᶜ``)."""

    def mass_and_forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> tuple[Float[Array, "n n"], Float[Array, " n"]]:
        """``(M, F_L)`` at one state."""
        return self.mass_matrix(system, q, qd, t, args), self.forces(system, q, qd, t, args)

    def mass_solver(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Factorization:
        """``b ↦ M⁻¹ b`` (vectors and matrices) at one state: by default `mass_matrix` factored
        by the system's ``mass_solve``. An implementation that applies ``M⁻¹`` without forming
        ``M`` (e.g. the articulated-body algorithm of a tree) overrides this and
        `solver_and_forces`; every solve of the equations of motion, of impacts and of the
        projections goes through them."""
        mass = self.mass_matrix(system, q, qd, t, args)
        return system.mass_solve.factor(mass, system.diagonal_mass)  # pyright: ignore[reportAttributeAccessIssue]

    def solver_and_forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> tuple[Factorization, Float[Array, " n"]]:
        """``(b ↦ M⁻¹ b, F_L)`` at one state (by default from `mass_and_forces`)."""
        mass, force = self.mass_and_forces(system, q, qd, t, args)
        return system.mass_solve.factor(mass, system.diagonal_mass), force  # pyright: ignore[reportAttributeAccessIssue]

    def dependence_mass(
        self,
        system: eqx.Module,
        q: Float[ArrayLike, " n"],  # NumPy zeros too: the analysis evaluates M on the side
        qd: Float[ArrayLike, " n"],
        t: Float[ArrayLike, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        """``M`` as the analysis of the structure of ``M`` reads it (which finds a constant
        ``M`` to invert once): the same values, written so that a ``M`` that does not depend on
        the state does not appear to."""
        return self.mass_matrix(system, jnp.asarray(q), jnp.asarray(qd), jnp.asarray(t), args)


class AutodiffDynamics(AbstractDynamics):
    r"""``M`` and ``F_L`` by automatic differentiation of ``L`` (the default).

    One ``jvp`` of the gradient ``(∂L/∂q, ∂L/∂q̇)`` along ``(q̇, 0, 1)`` in ``(q, q̇, t)`` gives
    ``∂L/∂q`` and ``(∂p/∂q) q̇ + ∂p/∂t``; n ``jvp``s of ``p = ∂L/∂q̇`` along the unit directions
    in ``q̇`` give ``M``. Cost ``O(n)`` evaluations of ``L``'s gradient per state.
    """

    def mass_matrix(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        return mass_along(system, q, qd, t, args, _unit_basis(qd))

    def forces(
        self,
        system: eqx.Module,
        q: Float[Array, " n"],
        qd: Float[Array, " n"],
        t: Float[Array, ""],
        args: Args,
    ) -> Float[Array, " n"]:
        dL_dq, _, dp_motion = _velocity_terms(system, q, qd, t, args)
        return dL_dq - dp_motion

    def dependence_mass(
        self,
        system: eqx.Module,
        q: Float[ArrayLike, " n"],  # NumPy zeros too: the analysis evaluates M on the side
        qd: Float[ArrayLike, " n"],
        t: Float[ArrayLike, ""],
        args: Args,
    ) -> Float[Array, "n n"]:
        # A plain identity: the hot path's basis is built from q̇ (so XLA cannot hoist it), which
        # would make every M look velocity-dependent.
        return mass_along(system, q, qd, t, args, jnp.eye(jnp.shape(q)[0], dtype=jnp.result_type(qd)))
