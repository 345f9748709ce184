r"""Structured Lagrangians as equinox Modules: plain LNN, DeLaN and the constrained (Cartesian) form.

Every model is an `equinox.Module` callable as ``L(q, q̇)``: a pytree of weights that
``jl.System(model)`` (or ``model.system()``) accepts as its Lagrangian directly, so that
``eqx.filter_grad`` with respect to the weights and ``jl.simulate`` both see the same object. The
equations of motion follow jaxlag's convention ``M q̈ = F + Jᵀλ`` with ``M = ∂²L/∂q̇²`` and
``J = ∂f/∂q`` for the known constraints ``f(q) = 0``.
"""

from collections.abc import Callable, Sequence
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from .._custom_types import Matrix, Scalar, Validated
from .._mechanics.mass_solve import RobustSolve
from .._system import System

Coordinates = Float[Array, " n"]
Velocities = Float[Array, " n"]


class AngleEmbedding(eqx.Module):
    r"""Features of the coordinates with the angles embedded on the circle.

    ``q ↦ (cos q_a, sin q_a, q_o)``: each coordinate listed in ``angles`` becomes its cosine and
    sine (so that a network of ``q`` is ``2π``-periodic in it), the other coordinates pass through.
    ``AngleEmbedding(angles=(0, 1))`` embeds the two angles of a double pendulum.
    """

    angles: tuple[int, ...] = eqx.field(static=True)

    def __init__(self, angles: int | Sequence[int]):
        if isinstance(angles, int):
            angles = (angles,)
        angles = tuple(int(i) for i in angles)
        if len(set(angles)) != len(angles) or any(i < 0 for i in angles):
            raise ValueError(f"AngleEmbedding: angles must be distinct non-negative indices; got {angles}.")
        self.angles = angles

    def size(self, n: int) -> int:
        """Number of features for ``n`` coordinates: ``n`` plus one per embedded angle."""
        bad = [i for i in self.angles if i >= n]
        if bad:
            raise ValueError(f"AngleEmbedding: angles {bad} are out of range for {n} coordinates.")
        return n + len(self.angles)

    def __call__(self, q: Coordinates) -> Float[Array, " features"]:
        n = q.shape[0]
        self.size(n)
        angles = jnp.asarray(self.angles, dtype=jnp.int32)
        others = jnp.asarray([i for i in range(n) if i not in self.angles], dtype=jnp.int32)
        return jnp.concatenate([jnp.cos(q[angles]), jnp.sin(q[angles]), q[others]])


def _features(embedding: AngleEmbedding | None, q: Coordinates) -> Array:
    return q if embedding is None else embedding(q)


def _in_size(embedding: AngleEmbedding | None, n: int) -> int:
    return n if embedding is None else embedding.size(n)


def _check_size(model: str, n: int, q: Array, qd: Array) -> None:
    """A clear error for data of another size than the model's (static shapes: at trace time)."""
    if jnp.shape(q) != (n,) or jnp.shape(qd) != (n,):
        raise ValueError(
            f"{model}: the model has n = {n} coordinates, but it was called with q of shape "
            f"{jnp.shape(q)} and qd of shape {jnp.shape(qd)}: the data's n (the last axis of "
            f"q, qd and qdd) must equal the model's n = {n}."
        )


class AbstractLagrangian(eqx.Module):
    r"""A learned Lagrangian ``L(q, q̇)``: an equinox Module of weights, callable as ``L(q, qd)``.

    `system` wraps it in a [`System`][jaxlag.System] (with the model's known constraints, if
    any), whose equations of motion are ``M q̈ = F + Jᵀλ``, ``M = ∂²L/∂q̇²``.
    """

    def __call__(self, q: Coordinates, qd: Velocities) -> Scalar:
        raise NotImplementedError

    def system(self, **kwargs: Any) -> System:
        """``jl.System(self, mass_solve=jl.RobustSolve(), **kwargs)``: the learned mode, in which a
        state whose learned ``M`` cannot be factored gives NaN (and a simulation ends with
        ``FailureCode.NONFINITE``) instead of raising. Keyword arguments go to
        [`System`][jaxlag.System]."""
        kwargs.setdefault("mass_solve", RobustSolve())
        return System(self, **kwargs)


class MLPLagrangian(AbstractLagrangian):
    r"""A plain Lagrangian neural network (Cranmer et al. 2020): ``L(q, q̇) = MLP(φ(q), q̇)``.

    ``φ`` is the optional `AngleEmbedding`. Nothing makes ``M = ∂²L/∂q̇²`` positive
    definite: where it is not, the learned accelerations of [`accelerations`][jaxlag.learned.accelerations]
    are NaN for that state (counted by the losses, never averaged in). The activation must be
    twice differentiable (default ``softplus``; ``relu`` has ``M = 0``).

    ``positive_output_init`` (default ``True``): the output layer's weights start non-negative
    (their absolute values), so that at initialization ``L`` is a positive combination of convex
    units of its last hidden layer: ``M`` is then positive definite at most states (all of them
    for ``depth=1``) and the acceleration loss has a gradient from the first step. With
    ``eqx.nn.MLP``'s own initialization ``M`` is indefinite at most states (394 of 512 random
    double-pendulum MLPs at one state), often at every training state, and training cannot
    start. Training may change the signs afterwards.
    """

    mlp: eqx.nn.MLP
    embedding: AngleEmbedding | None

    def __init__(
        self,
        n: int,
        width: int = 64,
        depth: int = 2,
        *,
        key: PRNGKeyArray,
        embedding: AngleEmbedding | None = None,
        activation: Callable = jax.nn.softplus,
        positive_output_init: bool = True,
    ):
        self.embedding = embedding
        mlp = eqx.nn.MLP(_in_size(embedding, n) + n, "scalar", width, depth, activation, key=key)
        if positive_output_init:
            mlp = eqx.tree_at(lambda m: m.layers[-1].weight, mlp, jnp.abs(mlp.layers[-1].weight))
        self.mlp = mlp

    @property
    def n(self) -> int:
        """The number of coordinates: the MLP reads ``φ(q)`` (``n`` plus one per embedded angle)
        and ``q̇`` (``n``)."""
        angles = 0 if self.embedding is None else len(self.embedding.angles)
        size = self.mlp.in_size
        assert isinstance(size, int)  # the MLP reads a vector, never a scalar
        return (size - angles) // 2

    def __call__(self, q: Coordinates, qd: Velocities) -> Scalar:
        _check_size("MLPLagrangian", self.n, q, qd)
        return self.mlp(jnp.concatenate([_features(self.embedding, q), qd]))


class DeLaN(AbstractLagrangian):
    r"""Deep Lagrangian network (Lutter et al. 2019): ``L = ½ q̇ᵀ M(q) q̇ − V(q)``.

    ``M(q) = C(q) C(q)ᵀ`` with ``C`` lower triangular: its diagonal is
    ``softplus(·) + floor`` and its strictly lower part is free, both read from one MLP of
    ``φ(q)``; so ``M`` is symmetric positive definite by construction for every weight and state
    (``C`` is invertible: ``det C = Π C_ii ≥ floorⁿ``). ``V(q)`` is a second MLP of ``φ(q)``
    (``φ`` the optional `AngleEmbedding`).

    That holds in exact arithmetic. In floating point ``M``'s condition number is ``κ(C)²``:
    where the network makes the off-diagonal of ``C`` dwarf its diagonal (e.g. entries ~40
    against the ``floor`` 10⁻³ gave ``κ(C) ≈ 6·10¹³``), ``M`` is singular to working precision,
    and the learned-mode solve ([`RobustSolve`][jaxlag.RobustSolve]) fails that state (NaN, counted)
    rather than return a wrong ``q̈``. A larger ``floor`` lowers ``κ``.
    """

    factor_net: eqx.nn.MLP
    potential_net: eqx.nn.MLP
    embedding: AngleEmbedding | None
    n: int = eqx.field(static=True)
    floor: float = eqx.field(static=True)

    def __init__(
        self,
        n: int,
        width: int = 64,
        depth: int = 2,
        *,
        key: PRNGKeyArray,
        embedding: AngleEmbedding | None = None,
        floor: float = 1e-3,
        activation: Callable = jax.nn.softplus,
    ):
        if not floor > 0:
            raise ValueError(f"DeLaN: floor must be positive (it bounds M's diagonal factor); got {floor}.")
        k1, k2 = jax.random.split(key)
        size = _in_size(embedding, n)
        self.n = int(n)
        self.floor = float(floor)
        self.embedding = embedding
        self.factor_net = eqx.nn.MLP(size, n * (n + 1) // 2, width, depth, activation, key=k1)
        self.potential_net = eqx.nn.MLP(size, "scalar", width, depth, activation, key=k2)

    def factor(self, q: Coordinates) -> Matrix:
        """``C(q)``: lower triangular with diagonal ``softplus(·) + floor > 0``."""
        out = self.factor_net(_features(self.embedding, q))
        n = self.n
        diagonal = jax.nn.softplus(out[:n]) + self.floor
        rows, cols = jnp.tril_indices(n, -1)
        lower = jnp.zeros((n, n), out.dtype).at[rows, cols].set(out[n:])
        return lower + jnp.diag(diagonal)

    def mass_matrix(self, q: Coordinates) -> Matrix:
        """``M(q) = C(q) C(q)ᵀ``, symmetric positive definite."""
        c = self.factor(q)
        return c @ c.T

    def potential(self, q: Coordinates) -> Scalar:
        """``V(q)``."""
        return self.potential_net(_features(self.embedding, q))

    def __call__(self, q: Coordinates, qd: Velocities) -> Scalar:
        _check_size("DeLaN", self.n, q, qd)
        v = self.factor(q).T @ qd
        return 0.5 * jnp.dot(v, v) - self.potential(q)


class ConstrainedLagrangian(AbstractLagrangian):
    r"""Constrained Lagrangian network (Finzi et al. 2020) in Cartesian coordinates.

    ``x = (x₁, …, x_B)`` stacks the positions of ``B`` bodies in ``dim`` dimensions and
    ``L(x, ẋ) = ½ Σ_b m_b |ẋ_b|² − V(x)``: learned masses ``m_b = softplus(ρ_b) + floor > 0``
    (so ``M = diag(m_b I_dim)`` is positive definite) and a learned potential MLP ``V(x)``. The
    known constraints ``f(x) = 0`` (``constraints(x) -> (m,)``, rigid rods, pivots) are imposed by
    jaxlag's KKT solve, ``M ẍ = F + Jᵀλ``, ``J ẍ = −γ``: `system` returns
    ``jl.System(self, holonomic=constraints, diagonal_mass=True)``.
    """

    raw_masses: Float[Array, " bodies"]
    potential_net: eqx.nn.MLP
    constraints: Callable = eqx.field(static=True)
    dim: int = eqx.field(static=True)
    floor: float = eqx.field(static=True)

    def __init__(
        self,
        bodies: int,
        dim: int,
        constraints: Validated[Callable],
        width: int = 64,
        depth: int = 2,
        *,
        key: PRNGKeyArray,
        floor: float = 1e-3,
        activation: Callable = jax.nn.softplus,
    ):
        if not callable(constraints):
            raise TypeError(
                f"ConstrainedLagrangian: constraints must be a function f(x); got {constraints!r}."
            )
        self.dim = int(dim)
        self.floor = float(floor)
        self.constraints = constraints
        # softplus(0.5413) = 1: unit masses at initialization.
        self.raw_masses = jnp.full((bodies,), 0.5413248546129181)
        self.potential_net = eqx.nn.MLP(bodies * dim, "scalar", width, depth, activation, key=key)

    def masses(self) -> Float[Array, " bodies"]:
        """``m_b = softplus(ρ_b) + floor``."""
        return jax.nn.softplus(self.raw_masses) + self.floor

    def potential(self, x: Coordinates) -> Scalar:
        """``V(x)``."""
        return self.potential_net(x)

    @property
    def n(self) -> int:
        """The number of coordinates, ``bodies · dim``."""
        return self.raw_masses.shape[0] * self.dim

    def __call__(self, q: Coordinates, qd: Velocities) -> Scalar:
        _check_size("ConstrainedLagrangian", self.n, q, qd)
        speeds = jnp.sum(qd.reshape(-1, self.dim) ** 2, axis=1)
        return 0.5 * jnp.dot(self.masses().astype(qd.dtype), speeds) - self.potential(q)

    def system(self, **kwargs: Any) -> System:
        """``jl.System(self, holonomic=self.constraints, diagonal_mass=True,
        mass_solve=jl.RobustSolve(), **kwargs)``."""
        kwargs.setdefault("diagonal_mass", True)
        kwargs.setdefault("mass_solve", RobustSolve())
        return System(self, holonomic=self.constraints, **kwargs)
