"""jaxlag: differentiable Lagrangian mechanics in JAX.

Write ``L(q, q̇)``; get the mass matrix, forces, constrained accelerations, multipliers and a
compiled, differentiable diffrax simulation. Sign convention everywhere:
``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Aᵀμ − ∂R/∂q̇ + Q``, i.e. ``M q̈ = F + Jᵀλ + Aᵀμ``.

Importing jaxlag changes no JAX setting; `enable_compilation_cache` is the opt-in for a
cross-process compilation cache. The sub-namespaces (``jaxlag.systems``, ``jaxlag.analysis``,
``jaxlag.learned`` with optax's training code, ``jaxlag.experimental`` with Pallas, ...) and the
fitting API (``jl.fit``, ``jl.Experiment``, ..., with optax) are imported on first use
(``jl.systems``, ``import jaxlag.systems``, ``jl.fit``, ``from jaxlag import fit``), so that a
script pays only for what it uses.
"""

import importlib
from typing import TYPE_CHECKING

from ._adjoint import ForwardSensitivities as ForwardSensitivities
from ._batch.batch import batch_sharding as batch_sharding
from ._batch.batch import simulate_batch as simulate_batch
from ._batch.ensemble import Ensemble as Ensemble
from ._batch.methods import AbstractBatchMethod as AbstractBatchMethod
from ._batch.vmap import Vmap as Vmap
from ._cache import (
    UnsafeCacheDirectory as UnsafeCacheDirectory,
)
from ._cache import (
    default_cache_directory as default_cache_directory,
)
from ._cache import (
    enable_compilation_cache as enable_compilation_cache,
)
from ._checks import Checks as Checks
from ._compile import compiler_options as compiler_options
from ._errors import AbstractOnFailure as AbstractOnFailure
from ._errors import FailureCode as FailureCode
from ._errors import NaNOnFailure as NaNOnFailure
from ._errors import RaiseOnFailure as RaiseOnFailure
from ._errors import SimulationError as SimulationError
from ._events import (
    Event as Event,
)
from ._events import (
    EventKind as EventKind,
)
from ._events import (
    EventLog as EventLog,
)
from ._events import (
    Events as Events,
)
from ._events import (
    multiplier_limit as multiplier_limit,
)
from ._mechanics.dynamics import (
    AbstractDynamics as AbstractDynamics,
)
from ._mechanics.dynamics import (
    AutodiffDynamics as AutodiffDynamics,
)
from ._mechanics.friction import Coulomb as Coulomb
from ._mechanics.impacts import Unilateral as Unilateral
from ._mechanics.mass_solve import (
    AbstractMassSolve as AbstractMassSolve,
)
from ._mechanics.mass_solve import (
    CheckedCholesky as CheckedCholesky,
)
from ._mechanics.mass_solve import (
    RobustSolve as RobustSolve,
)
from ._options import SimulateOptions as SimulateOptions
from ._simulate import simulate as simulate
from ._solver.rk4 import RK4 as RK4
from ._stabilization import (
    Baumgarte as Baumgarte,
)
from ._stabilization import (
    Projection as Projection,
)
from ._stabilization import (
    consistent_initial_state as consistent_initial_state,
)
from ._system import System as System
from ._trajectory import Trajectory as Trajectory
from ._variational import (
    AbstractVariationalMethod as AbstractVariationalMethod,
)
from ._variational import (
    Rattle as Rattle,
)
from ._variational import (
    VariationalMidpoint as VariationalMidpoint,
)
from ._variational import (
    simulate_variational as simulate_variational,
)
from ._vector_field import EquationsOfMotion as EquationsOfMotion

__version__ = "0.1.0"

if TYPE_CHECKING:
    from . import analysis as analysis
    from . import contact as contact
    from . import coordinates as coordinates
    from . import experimental as experimental
    from . import inputs as inputs
    from . import learned as learned
    from . import loads as loads
    from . import plot as plot
    from . import rotations as rotations
    from . import systems as systems
    from ._fit.combinations import IdentifiableCombination as IdentifiableCombination
    from ._fit.data import Experiment as Experiment
    from ._fit.fit import fit as fit
    from ._fit.fit import least_squares_loss as least_squares_loss
    from ._fit.options import Bounded as Bounded
    from ._fit.options import FitWarning as FitWarning
    from ._fit.options import MultiStart as MultiStart
    from ._fit.options import Positive as Positive
    from ._fit.options import Shooting as Shooting
    from ._fit.statistics import FitResult as FitResult

#: Subpackages imported on first access (PEP 562), not by ``import jaxlag``.
_ON_FIRST_USE = (
    "analysis",
    "contact",
    "coordinates",
    "experimental",
    "inputs",
    "learned",
    "loads",
    "plot",
    "rotations",
    "systems",
)


#: The fitting API (and optax, which it imports), loaded on first access: name -> module.
_FIT_ON_FIRST_USE = {
    "Bounded": "._fit.options",
    "Experiment": "._fit.data",
    "FitResult": "._fit.statistics",
    "FitWarning": "._fit.options",
    "IdentifiableCombination": "._fit.combinations",
    "MultiStart": "._fit.options",
    "Positive": "._fit.options",
    "Shooting": "._fit.options",
    "fit": "._fit.fit",
    "least_squares_loss": "._fit.fit",
}


def __getattr__(name: str):
    if name in _ON_FIRST_USE:
        return importlib.import_module(f"{__name__}.{name}")
    if name in _FIT_ON_FIRST_USE:
        value = getattr(importlib.import_module(_FIT_ON_FIRST_USE[name], __name__), name)
        globals()[name] = value  # later lookups skip __getattr__
        return value
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__() -> list[str]:
    return sorted({*globals(), *_ON_FIRST_USE, *_FIT_ON_FIRST_USE})
