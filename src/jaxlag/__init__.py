"""jaxlag: differentiable Lagrangian mechanics in JAX.

Write ``L(q, q̇)``; get the mass matrix, forces, constrained accelerations, multipliers and a
compiled, differentiable diffrax simulation. Sign convention everywhere:
``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Aᵀμ − ∂R/∂q̇ + Q``, i.e. ``M q̈ = F + Jᵀλ + Aᵀμ``.
"""

from . import analysis, compilation, contact, coordinates, loads, rotations, systems
from .batch import batch_sharding, simulate_batch
from .compilation import compiler_options
from .ensemble import RK4
from .conventions import UserFunction
from .events import Event, EventLog, multiplier_limit
from .failures import SimulationError
from .fit import Bounded, Experiment, FitResult, Positive, fit, least_squares_loss
from .kkt import solve_kkt
from .sensitivities import ForwardSensitivities
from .simulate import EquationsOfMotion, simulate
from .stabilization import Baumgarte, ProjectedSolver, Projection, consistent_initial_state
from .system import System
from .trajectory import Trajectory
from .variational import simulate_variational

__all__ = [
    "analysis",
    "compilation",
    "batch_sharding",
    "simulate_batch",
    "contact",
    "coordinates",
    "loads",
    "rotations",
    "systems",
    "Baumgarte",
    "Bounded",
    "EquationsOfMotion",
    "Event",
    "EventLog",
    "Experiment",
    "FitResult",
    "ForwardSensitivities",
    "Positive",
    "ProjectedSolver",
    "Projection",
    "RK4",
    "SimulationError",
    "System",
    "Trajectory",
    "UserFunction",
    "compiler_options",
    "consistent_initial_state",
    "fit",
    "least_squares_loss",
    "multiplier_limit",
    "simulate",
    "simulate_variational",
    "solve_kkt",
]

__version__ = "0.1.0"

compilation.enable_persistent_cache()
