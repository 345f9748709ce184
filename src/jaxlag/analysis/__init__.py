"""Analysis tools in one namespace: equilibria, linearization and normal modes, conservation laws.

``jaxlag.analysis`` gathers equilibria, linearization and normal modes, and conservation laws
(each a small private module with one job)::

    from jaxlag import analysis
    eq = analysis.equilibrium(system, q_guess, args=args)
    lin = analysis.linearize(system, eq.q, eq.qd, args=args)
    lin.frequencies, lin.stability()
    modes = analysis.normal_modes(system, eq.q, args=args)
    analysis.conservation_report(trajectory, {"L_z": analysis.rotation_generator([0, 0, 1])})
"""

from ._conservation import (
    ConservedQuantity,
    conservation_report,
    energy,
    format_report,
    ignorable_coordinates,
    momenta,
    noether_charge,
    noether_rate,
    rotation_generator,
    translation_generator,
)
from ._equilibria import Equilibrium, equilibrium
from ._linearize import Linearization, NormalModes, linearize, normal_modes, tangent_basis

__all__ = [
    "ConservedQuantity",
    "Equilibrium",
    "Linearization",
    "NormalModes",
    "conservation_report",
    "energy",
    "equilibrium",
    "format_report",
    "ignorable_coordinates",
    "linearize",
    "momenta",
    "noether_charge",
    "noether_rate",
    "normal_modes",
    "rotation_generator",
    "tangent_basis",
    "translation_generator",
]
