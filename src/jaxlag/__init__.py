"""jaxlag: differentiable Lagrangian mechanics in JAX.

Write ``L(q, q̇)``; get the mass matrix, forces, constrained accelerations, multipliers and a
compiled, differentiable diffrax simulation. Sign convention everywhere:
``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Aᵀμ − ∂R/∂q̇ + Q``, i.e. ``M q̈ = F + Jᵀλ + Aᵀμ``.

Importing jaxlag changes no JAX setting; :func:`enable_compilation_cache` is the opt-in for a
cross-process compilation cache.
"""

from . import (
    analysis as analysis,
    contact as contact,
    coordinates as coordinates,
    experimental as experimental,
    inputs as inputs,
    learned as learned,
    loads as loads,
    plot as plot,
    rotations as rotations,
    systems as systems,
)
from ._adjoint import ForwardSensitivities as ForwardSensitivities
from ._batch.batch import batch_sharding as batch_sharding, simulate_batch as simulate_batch
from ._batch.ensemble import Ensemble as Ensemble
from ._batch.methods import AbstractBatchMethod as AbstractBatchMethod
from ._batch.vmap import Vmap as Vmap
from ._cache import (
    UnsafeCacheDirectory as UnsafeCacheDirectory,
    default_cache_directory as default_cache_directory,
    enable_compilation_cache as enable_compilation_cache,
)
from ._checks import Checks as Checks
from ._compile import compiler_options as compiler_options
from ._errors import FailureCode as FailureCode, SimulationError as SimulationError
from ._events import (
    Event as Event,
    EventKind as EventKind,
    EventLog as EventLog,
    Events as Events,
    multiplier_limit as multiplier_limit,
)
from ._mechanics.friction import Coulomb as Coulomb
from ._mechanics.impacts import Unilateral as Unilateral
from ._fit.data import Experiment as Experiment
from ._fit.fit import fit as fit, least_squares_loss as least_squares_loss
from ._fit.options import (
    Bounded as Bounded,
    FitWarning as FitWarning,
    MultiStart as MultiStart,
    Positive as Positive,
    Shooting as Shooting,
)
from ._fit.statistics import FitResult as FitResult
from ._options import SimulateOptions as SimulateOptions
from ._simulate import simulate as simulate
from ._solver.rk4 import RK4 as RK4
from ._stabilization import (
    Baumgarte as Baumgarte,
    Projection as Projection,
    consistent_initial_state as consistent_initial_state,
)
from ._mechanics.mass_solve import (
    AbstractMassSolve as AbstractMassSolve,
    CheckedCholesky as CheckedCholesky,
    RobustSolve as RobustSolve,
)
from ._system import System as System
from ._trajectory import Trajectory as Trajectory
from ._variational import (
    AbstractVariationalMethod as AbstractVariationalMethod,
    Rattle as Rattle,
    simulate_variational as simulate_variational,
    VariationalMidpoint as VariationalMidpoint,
)
from ._vector_field import EquationsOfMotion as EquationsOfMotion

__version__ = "0.1.0"
