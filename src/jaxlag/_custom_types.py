"""Type aliases of jaxlag's public signatures: jaxtyping shapes, in the style of diffrax's.

Dimension names follow the physics: ``n`` generalized coordinates, ``m`` multipliers (one per
constraint row), ``times`` save times, ``*batch`` the leading axes of a batched result. Inputs
accept ``ArrayLike`` (NumPy arrays, Python numbers); results are JAX arrays. Annotations only:
nothing is checked at runtime, and to a static type checker ``Float[X, "..."]`` is just ``X``.
"""

from collections.abc import Callable, Sequence
from typing import TYPE_CHECKING, Annotated, TypeVar

import numpy as np
from jaxtyping import Array, ArrayLike, Float, PyTree, Real

# A real scalar: a Python number or a 0-d array (a time, a rate, a tolerance). As in diffrax: a
# plain union for the type checker, a jaxtyping 0-d shape at runtime.
if TYPE_CHECKING:
    RealScalarLike = bool | int | float | Array | np.ndarray
else:
    RealScalarLike = Real[ArrayLike, ""]

_T = TypeVar("_T")

# An argument that jaxlag checks itself, raising an error whose message names the fix
# (``projection="auto"``, ``checks=False``, ``events=[event, 3]``): ``Validated[X]`` is ``X`` to
# the static type checker, and at run time admits any value (``Annotated[object, ..., X]``: a
# run-time type checker sees ``object``), so that a run-time type checker (the test suite's) lets
# jaxlag's own message through instead of replacing it.
if TYPE_CHECKING:
    Validated = Annotated[_T, "checked by jaxlag"]
else:

    class Validated:
        def __class_getitem__(cls, item):
            return Annotated[object, "checked by jaxlag", item]


Args = PyTree  #: any pytree of parameters, passed as ``args`` to every user function that declares it.
# An array given as an input: a JAX or NumPy array of real numbers, a Python number, or a
# (nested) list or tuple of them, converted with ``jnp.asarray`` (integers are promoted to
# float). Any shape is admitted here: jaxlag checks the shapes itself, with messages that name
# the fix (``q0`` and ``qd0`` 1-D and of the same length), so the dimension names of the
# aliases below are their documentation. (``jax.typing.ArrayLike`` excludes lists; jaxlag's
# inputs, like diffrax's ``y0``, a pytree of numbers, do not.)
RealArrayLike = Real[ArrayLike, "..."] | Sequence
#: a number, an array (or a list of numbers), or a function of ``args`` returning one.
Parameter = RealArrayLike | Callable[[Args], ArrayLike]
Coordinates = RealArrayLike  #: generalized coordinates ``q`` given as an input, shape ``(n,)``.
Velocities = RealArrayLike  #: generalized velocities ``q̇`` given as an input, shape ``(n,)``.
Vector = Float[Array, " n"]  #: ``q``, ``q̇``, ``q̈``, momenta or generalized forces at one instant.
Matrix = Float[Array, "n n"]  #: a matrix over the coordinates: mass matrix ``M``, stiffness ``K``.
Scalar = Float[Array, ""]  #: a real scalar result: an energy, a Lagrangian value, a residual.
SaveTimes = RealArrayLike  #: increasing save times ``ts`` given as an input, shape ``(times,)``.
Times = Float[Array, "*batch times"]  #: the saved times of a trajectory.
States = Float[Array, "*batch times n"]  #: saved coordinates or velocities, one row per save time.
Multipliers = Float[Array, "*batch times m"]  #: saved multipliers ``λ`` or ``μ``, one row per save time.

__all__ = [
    "Args",
    "Coordinates",
    "Matrix",
    "Multipliers",
    "Parameter",
    "RealArrayLike",
    "RealScalarLike",
    "SaveTimes",
    "Scalar",
    "States",
    "Times",
    "Validated",
    "Vector",
    "Velocities",
]
