"""Type aliases of jaxlag's public signatures: jaxtyping shapes, in the style of diffrax's.

Dimension names follow the physics: ``n`` generalized coordinates, ``m`` multipliers (one per
constraint row), ``times`` save times, ``*batch`` the leading axes of a batched result. Inputs
accept ``ArrayLike`` (NumPy arrays, Python numbers); results are JAX arrays. Annotations only:
nothing is checked at runtime, and to a static type checker ``Float[X, "..."]`` is just ``X``.
"""

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree, Real

# A real scalar: a Python number or a 0-d array (a time, a rate, a tolerance). As in diffrax: a
# plain union for the type checker, a jaxtyping 0-d shape at runtime.
if TYPE_CHECKING:
    RealScalarLike = bool | int | float | Array | np.ndarray
else:
    RealScalarLike = Real[ArrayLike, ""]

Args = PyTree  #: any pytree of parameters, passed as ``args`` to every user function that declares it.
Parameter = ArrayLike | Callable[[Args], ArrayLike]  #: a number or array, or a function of ``args``.
Coordinates = Float[ArrayLike, " n"]  #: generalized coordinates ``q`` given as an input.
Velocities = Float[ArrayLike, " n"]  #: generalized velocities ``q̇`` given as an input.
Vector = Float[Array, " n"]  #: ``q``, ``q̇``, ``q̈``, momenta or generalized forces at one instant.
Matrix = Float[Array, "n n"]  #: a matrix over the coordinates: mass matrix ``M``, stiffness ``K``.
Scalar = Float[Array, ""]  #: a real scalar result: an energy, a Lagrangian value, a residual.
SaveTimes = Float[ArrayLike, " times"]  #: increasing save times ``ts`` given as an input.
Times = Float[Array, "*batch times"]  #: the saved times of a trajectory.
States = Float[Array, "*batch times n"]  #: saved coordinates or velocities, one row per save time.
Multipliers = Float[Array, "*batch times m"]  #: saved multipliers ``λ`` or ``μ``, one row per save time.

__all__ = [
    "Args",
    "Coordinates",
    "Matrix",
    "Multipliers",
    "Parameter",
    "RealScalarLike",
    "SaveTimes",
    "Scalar",
    "States",
    "Times",
    "Vector",
    "Velocities",
]
