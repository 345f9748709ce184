"""The equations of motion as a diffrax vector field: ``(q, q̇) ↦ (q̇, q̈)``.

``q̈`` solves ``M q̈ = F + Jᵀλ`` (with ``J q̈ = −γ`` and optional Baumgarte feedback) for a
constrained system, ``M q̈ = F`` otherwise; with Coulomb friction in a given stick/slip mode
``M q̈ = F + Jᵀλ + Tᵀλ_t`` (`jaxlag._mechanics.friction`).
"""

import equinox as eqx
from jaxtyping import Array, Bool, Float

from . import _compile as compilation
from ._conventions import as_jit_inputs
from ._custom_types import Args, RealScalarLike, Vector
from ._mechanics.friction import solve_with_modes
from ._mechanics.kkt import accelerations_and_multipliers
from ._mechanics.lagrangian import unconstrained_accelerations
from ._stabilization import Baumgarte
from ._system import System


class EquationsOfMotion(eqx.Module):
    """The first-order vector field ``(q, q̇) ↦ (q̇, q̈)`` as a diffrax-compatible callable.

    A module (not a closure) so that repeated ``simulate`` calls hit diffrax's compilation cache.
    """

    system: System
    baumgarte: Baumgarte | None = None
    active: Bool[Array, " m_h"] | None = None  # holonomic activity mask while unilateral constraints are off
    # Friction mode per Coulomb contact (0 stick, ±1 slip; jaxlag._mechanics.friction), or None.
    modes: Float[Array, " k"] | None = None

    def __call__(self, t: RealScalarLike, y: tuple[Vector, Vector], args: Args) -> tuple[Vector, Vector]:
        if self.system.friction and self.modes is None:
            raise ValueError(
                "This system has Coulomb friction (jl.Coulomb), whose equations depend on the "
                "stick/slip mode of each contact: jl.simulate integrates it (in segments between "
                "the switches); pass EquationsOfMotion(system, baumgarte, active, modes) to use "
                "the field directly. The ensemble and variational integrators do not support it."
            )
        t, args = as_jit_inputs(t, args, y[0].dtype)
        # Jitted: diffrax's term check, its first step size and the solver step (each traces the
        # field) share one trace of the equations of motion; XLA inlines the call.
        return _equations_of_motion(self, t, y, args)


# jaxlag's jit: keyed on the compiled checks' choice in force (checks inside the user's functions),
# compiled with jaxlag's options when called eagerly.
@compilation.filter_jit
def _equations_of_motion(field: EquationsOfMotion, t, y, args):
    """`EquationsOfMotion.__call__`."""
    q, qd = y
    system = field.system
    if field.modes is not None and system.friction:
        qdd = solve_with_modes(system, q, qd, t, args, field.baumgarte, field.active, field.modes)[0]
    elif system.is_constrained:
        qdd = accelerations_and_multipliers(system, q, qd, t, args, field.baumgarte, field.active)[0]
    else:
        qdd = unconstrained_accelerations(system, q, qd, t, args)
    return qd, qdd
