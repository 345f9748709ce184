r"""Linearization about an equilibrium or a steady motion; normal modes; stability.

**State space.** With ``y = (q, q̇)`` the equations of motion are ``ẏ = X(y, u) = (q̇, q̈(q, q̇, u))``
(``q̈`` from the constrained KKT solve, sign convention ``M q̈ = F + Q_u(q, q̇, u, t) + Jᵀλ + Aᵀμ``).
Their linearization about ``(y*, u₀)`` is ``δẏ = A δy + B δu`` with ``A = ∂X/∂y`` (2n × 2n, by
``jax.jacfwd``, the input held at ``u₀``: the open loop) and ``B = ∂X/∂u`` (2n × k): for a system
with an ``actuation`` ``Q_u``, ``B = (0, M_c⁻¹ ∂Q_u/∂u)`` with ``M_c⁻¹`` the constrained inverse
of the KKT solve; or, with ``inputs=``, the derivative with respect to a value selected in
``args``. ``u₀`` is ``u=`` if given, else the system's control law at ``(y*, t)``. A control law
``u = κ(y, t)`` also gives the feedback matrix ``F = ∂κ/∂y`` (k × 2n) and the closed loop
``δẏ = (A + B F) δy``: an LQR gain ``u = −K y`` has ``F = −K``.

**Constraints.** The motion stays on the manifold ``C(y) = (f, ḟ, g) = 0`` (holonomic position
and velocity level, velocity constraints). Its tangent space at ``y*`` is ``T = null(∂C/∂y)``, of
dimension ``d = 2n − 2m_h − m_v``; the exact constrained flow leaves the manifold invariant, so
``A`` maps ``T`` into itself and the motion near ``y*`` is ``δẏ = A|_T δy``. jaxlag forms a basis
``E`` (2n × d) of ``T`` and the reduced matrices ``A_T = E⁺ A E``, ``B_T = E⁺ B`` (``E⁺`` the
left inverse), ``F_T = F E``. ``B`` lies in ``T`` exactly (the input changes ``q̈`` only, and
within ``J δq̈ = 0``), so ``E B_T = B``. Directions off the manifold (``δf ≠ 0``) carry only the spurious zero
eigenvalues of the index-1 equations and are removed. ``E`` is the orthonormal null-space basis
of an SVD, carried along by the projector ``P = I − Cᵀ(CCᵀ)⁻¹C`` so that its derivative exists:
eigenvalues, frequencies and their gradients do not depend on which basis is chosen.

**Spectrum.** Eigenvalues ``s`` of ``A_T``: an oscillation at frequency ``ω`` is the pair
``s = ±iω``, an unstable direction ``s > 0``, a symmetry (cyclic coordinate, family of
equilibria) ``s = 0``. For a conservative system the ``d`` eigenvalues come in pairs, so
``frequencies`` are the ``d/2`` values ``|Im s|`` (each taken once). The verdict:

* ``"unstable"``: some ``Re s > tol``;
* ``"asymptotically stable"``: every ``Re s < −tol`` (damped);
* ``"stable"``: every eigenvalue on the imaginary axis and none zero (a linear centre; for a
  conservative system this is linear, not yet nonlinear, stability);
* ``"marginal"``: on the imaginary axis with some zero eigenvalues (symmetry directions or a
  family of equilibria; e.g. a circular orbit in ``(r, φ)``); a higher-order analysis decides.

``tol`` is ``tolerance`` (default ``1e-6``) times the norm of ``A_T`` (the zero eigenvalues of
a Jordan block are computed only to about ``√ε`` relative accuracy).

**Time dependence.** For a time-dependent system (explicit ``t`` in ``L``, rheonomic constraints)
the matrices are those of the variational equation frozen at ``t``. Their eigenvalues decide
stability when they are the same at every time along the motion: choose coordinates in which the
steady motion is a uniform drift of cyclic coordinates (the spinning-wire bead in ``(r, φ, z)``
with ``φ = ωt``, not in inertial Cartesian coordinates, where the tangent space itself rotates).

**Normal modes** (`normal_modes`, equilibria at rest): with ``E_q`` a basis of
``null(J)`` the small oscillations solve ``K_T v = ω² M_T v`` with ``M_T = E_qᵀ M E_q`` and
``K_T = −E_qᵀ M (∂q̈/∂q) E_q``, which includes the constraint curvature ``Σ λ_i ∂²f_i/∂q²``
(the tension of a Cartesian pendulum is its restoring force). A symmetric generalized eigenproblem
(Cholesky of ``M_T``, ``eigh``) gives real ``ω²`` and ``M``-orthonormal shapes, differentiable
with ``jax.grad``. Negative ``ω²`` are unstable directions (Lagrange–Dirichlet: all positive is
stable for natural systems).
"""

from collections.abc import Callable

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, ArrayLike, Bool, Complex, Float

from .. import _compile as compilation
from .._conventions import UserFunction, as_array_leaves, as_float_state
from .._custom_types import Args, Coordinates, RealScalarLike, Scalar, Vector, Velocities
from .._errors import compiled_check
from .._mechanics import constraints as _constraints
from .._mechanics import kkt as _kkt
from .._mechanics import lagrangian as _mechanics
from .._misc import is_concrete
from .._system import System, check_input_shape
from .._tolerances import CONSTRAINT_RCOND

__all__ = ["Linearization", "NormalModes", "linearize", "normal_modes", "tangent_basis"]


def tangent_basis(jacobian: Float[Array, "m k"]) -> Float[Array, "k k-m"]:
    """A basis ``E`` (k × (k − m)) of ``null(jacobian)`` for a full-row-rank ``jacobian`` (m × k).

    Orthonormal at the point (an SVD); its derivative is that of ``P E₀`` with the projector
    ``P = I − Cᵀ(CCᵀ)⁻¹C``, so gradients through it are well defined.
    """
    m, k = jacobian.shape
    if m == 0:
        return jnp.eye(k, dtype=jacobian.dtype)
    _, _, vt = jnp.linalg.svd(jax.lax.stop_gradient(jacobian), full_matrices=True)
    reference = vt[m:].T
    gram = jacobian @ jacobian.T
    correction = jacobian.T @ jnp.linalg.solve(gram, jacobian @ reference)
    return reference - correction


def _state_constraints(system, q, qd, t, args):
    f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
    return jnp.concatenate([f, f_dot, g])


def _constraint_rank_check(jacobian):
    if jacobian.shape[0] == 0:
        return jnp.asarray(False)
    sv = jnp.linalg.svd(jacobian, compute_uv=False)
    return ~(sv[-1] > CONSTRAINT_RCOND * sv[0])


def _left_inverse(basis):
    return jnp.linalg.solve(basis.T @ basis, basis.T)


def _accelerations(system, q, qd, t, args):
    if system.is_constrained:
        return _kkt.accelerations_and_multipliers(system, q, qd, t, args)[0]
    return _mechanics.unconstrained_accelerations(system, q, qd, t, args)


def _raise_rank(kind):
    return ValueError(
        f"The {kind} constraint Jacobian is rank deficient at this state (redundant "
        "constraints): the constraint manifold's tangent space is not defined by them. Remove "
        "the redundant constraints."
    )


def _spectrum_tol(matrix, tolerance, xp=jnp):
    # Relative to the size of the matrix, not of its spectrum: a nilpotent block (a family of
    # equilibria) has all eigenvalues ≈ 0, computed only to about √ε·‖A‖. ``xp``: NumPy on the
    # host (`Linearization.stability`), where jax.numpy would compile a program per operation.
    return tolerance * xp.max(xp.sum(xp.abs(matrix), axis=1), initial=0.0) + 1e-300


class Linearization(eqx.Module):
    r"""``δẏ = A δy + B δu`` about ``(q, q̇)`` and the input ``u₀`` at time ``t``, ``y = (q, q̇)``.

    - ``state_matrix`` ``A`` (2n × 2n, the open loop: ``u`` held at ``u₀``) and ``input_matrix``
      ``B`` (2n × k, or ``None``) in the full coordinates;
    - ``basis`` ``E`` (2n × d) of the constraint manifold's tangent space (the identity for an
      unconstrained system);
    - ``reduced_state_matrix`` ``A_T`` (d × d), ``reduced_input_matrix`` ``B_T`` (d × k): the
      same dynamics in the coordinates ``δy = E z`` of the tangent space;
    - ``input`` ``u₀`` (scalar or (k,), or ``None`` without actuation) and ``feedback_matrix``
      ``F = ∂κ/∂y`` (k × 2n) of the system's control law ``u = κ(y, t)`` (``None`` without one).

    Spectral quantities use ``A_T`` (the open loop); ``closed_loop_eigenvalues`` those of
    ``A_T + B_T F E``. See the module docstring for the stability verdict.
    """

    q: Vector
    qd: Vector
    t: Scalar
    state_matrix: Float[Array, "two_n two_n"]
    input_matrix: Float[Array, "two_n k"] | None
    basis: Float[Array, "two_n d"]
    reduced_state_matrix: Float[Array, "d d"]
    reduced_input_matrix: Float[Array, "d k"] | None
    input: Float[Array, " *k"] | None = None
    feedback_matrix: Float[Array, "k two_n"] | None = None

    @property
    def eigenvalues(self) -> Complex[Array, " d"]:
        """Eigenvalues of ``A_T`` (complex), ordered by imaginary part, then real part."""
        return _ordered_eigenvalues(self.reduced_state_matrix)

    @property
    def closed_loop_matrix(self) -> Float[Array, "two_n two_n"]:
        """``A + B F``: the state matrix with the control law's feedback ``δu = F δy``."""
        return _closed_loop(self.state_matrix, self._feedback_input(), self._feedback(), None)

    @property
    def reduced_closed_loop_matrix(self) -> Float[Array, "d d"]:
        """``A_T + B_T F E``: the closed loop on the tangent space of the constraint manifold."""
        reduced_input = self.reduced_input_matrix
        if reduced_input is None:
            raise ValueError(_NO_INPUT)
        return _closed_loop(self.reduced_state_matrix, reduced_input, self._feedback(), self.basis)

    @property
    def closed_loop_eigenvalues(self) -> Complex[Array, " d"]:
        """Eigenvalues of ``A_T + B_T F E`` (complex), ordered as `eigenvalues`."""
        return _ordered_eigenvalues(self.reduced_closed_loop_matrix)

    def _feedback(self) -> Float[Array, "k two_n"]:
        if self.feedback_matrix is None:
            raise ValueError(
                "No feedback matrix: the system has no control law (give jl.System(..., "
                "control=law) or system.with_control(law) before linearizing)."
            )
        return self.feedback_matrix

    def _feedback_input(self) -> Float[Array, "two_n k"]:
        if self.input_matrix is None:
            raise ValueError(_NO_INPUT)
        return self.input_matrix

    def modes(self) -> tuple[Complex[Array, " d"], Complex[Array, "two_n d"]]:
        """``(eigenvalues, shapes)``: shapes (2n × d, complex) are eigenvectors in full ``(δq, δq̇)``."""
        values, vectors = jnp.linalg.eig(self.reduced_state_matrix)
        return values, self.basis.astype(vectors.dtype) @ vectors

    @property
    def frequencies(self) -> Float[Array, " pairs"]:
        """The ``d/2`` angular frequencies ``|Im s|`` (ascending; zeros for non-oscillating pairs)."""
        return _frequencies(self.reduced_state_matrix)

    @property
    def growth_rate(self) -> Scalar:
        """``max Re s``: positive for an unstable state."""
        return _growth_rate(self.reduced_state_matrix)

    def is_stable(self, tolerance: float = 1e-6) -> Bool[Array, ""]:
        """``max Re s ≤ tol`` (spectral stability) as a boolean array (works under ``jit``)."""
        return _is_stable(self.reduced_state_matrix, jnp.asarray(tolerance, self.reduced_state_matrix.dtype))

    def stability(self, tolerance: float = 1e-6) -> str:
        """``"unstable"``, ``"asymptotically stable"``, ``"stable"`` or ``"marginal"`` (concrete
        values only; under ``jit`` use `is_stable`)."""
        matrix = np.asarray(self.reduced_state_matrix)
        values = np.linalg.eigvals(matrix)
        if values.size == 0:
            return "marginal"
        tol = float(_spectrum_tol(matrix, tolerance, np))
        re = values.real
        if np.any(re > tol):
            return "unstable"
        if np.all(re < -tol):
            return "asymptotically stable"
        if np.any(np.abs(values) <= tol):
            return "marginal"
        return "stable"


_NO_INPUT = "No input matrix: the system has no actuation and no `inputs=` was given."


# The spectral quantities are one program each for given shapes (called eagerly, each
# jax.numpy operation would compile a program of its own); inside a jit they are inlined.
@compilation.filter_jit
def _ordered_eigenvalues(matrix):
    values = jnp.linalg.eigvals(matrix)
    return values[jnp.lexsort((jnp.real(values), jnp.imag(values)))]


@compilation.filter_jit
def _closed_loop(state_matrix, input_matrix, feedback, basis):
    """``A + B F`` (``basis`` None), or ``A_T + B_T F E`` on the tangent space."""
    gain = feedback if basis is None else feedback @ basis
    return state_matrix + input_matrix @ gain


@compilation.filter_jit
def _frequencies(matrix):
    mags = jnp.sort(jnp.abs(jnp.imag(jnp.linalg.eigvals(matrix))))
    return mags[::2] if mags.shape[0] % 2 == 0 else mags[1::2]


@compilation.filter_jit
def _growth_rate(matrix):
    return jnp.max(jnp.real(jnp.linalg.eigvals(matrix)), initial=-jnp.inf)


@compilation.filter_jit
def _is_stable(matrix, tolerance):
    values = jnp.linalg.eigvals(matrix)
    return jnp.max(jnp.real(values), initial=-jnp.inf) <= _spectrum_tol(matrix, tolerance)


def _input_derivative(field, args, inputs):
    u0 = jnp.asarray(inputs(args))
    shape = u0.shape
    if u0.ndim > 1:
        raise ValueError(
            f"The input selected by `inputs` must be a scalar or a 1-D array; got shape {shape}."
        )
    if not jnp.issubdtype(u0.dtype, jnp.floating):
        u0 = u0.astype(jnp.result_type(float))
    flat = jnp.atleast_1d(u0)

    def with_input(u):
        value = u.reshape(shape)
        return field(eqx.tree_at(inputs, args, value, is_leaf=lambda x: x is None))

    return jax.jacfwd(with_input)(flat)


def linearize(
    system: System,
    q: Coordinates,
    qd: Velocities | None = None,
    t: RealScalarLike = 0.0,
    args: Args = None,
    *,
    u: Float[ArrayLike, " *k"] | None = None,
    inputs: Callable | None = None,
) -> Linearization:
    r"""Linearize the equations of motion about ``(q, q̇)`` at time ``t``.

    - ``q``, ``qd``: the state (``qd`` defaults to rest); typically from
      [`jaxlag.analysis.equilibrium`][jaxlag.analysis.equilibrium]. Any state may be given: about a
      non-equilibrium
      state the matrices describe the variational equation at that instant.
    - ``u``: for a system with an ``actuation`` ``Q_u(q, q̇, u, t)``, the input ``u₀`` (scalar or
      (k,)) about which to linearize; by default the system's control law at the state,
      ``u₀ = κ(q, q̇, t)``. ``state_matrix`` is the open loop (``u`` held at ``u₀``),
      ``input_matrix`` ``B = ∂(q̇, q̈)/∂u`` (2n × k, k = 1 for a scalar input) and, when the
      system has a control law, ``feedback_matrix`` ``F = ∂κ/∂(q, q̇)`` gives the closed loop
      (``closed_loop_eigenvalues``).
    - ``inputs``: optional ``where``-function selecting an input inside ``args`` instead (as in
      ``eqx.tree_at``), e.g. ``lambda a: a["force"]``; then ``input_matrix`` is ``∂ẏ/∂a`` for
      that value (through the control law evaluated at the state, if it reads it) and there is no
      ``feedback_matrix``.

    Returns a `Linearization`. Works under ``jit``, ``vmap`` and ``grad`` (eigenvalues
    and frequencies are differentiable; nonsymmetric eigen-decompositions run on the CPU).
    """
    q, qd = as_float_state(q, jnp.zeros_like(jnp.asarray(q)) if qd is None else qd)
    qd = qd.astype(q.dtype)
    args = as_array_leaves(args, q.dtype)  # new parameter values must not recompile
    system.check(q, qd, t, args)
    t = jnp.asarray(t, q.dtype)
    if u is not None:
        if system.actuation is None:
            raise ValueError(
                "linearize: u= was given, but the system has no `actuation` Q_u(q, qd, u) through "
                "which an input acts; give jl.System(..., actuation=...) (or select an input in "
                "args with inputs=)."
            )
        u = jnp.asarray(u)
        if not jnp.issubdtype(u.dtype, jnp.floating):
            u = u.astype(q.dtype)
        check_input_shape(system, q, qd, u, t, args, "linearize's u=")
        u = u.astype(q.dtype)
    elif system.actuation is not None and system.control is None:
        raise ValueError(
            "linearize: the system has an actuation Q_u(q, qd, u) but no control law; give the "
            "input to linearize about, e.g. u=0.0 (or u=jnp.zeros(k)), or a control law."
        )
    lin, rank_deficient = _linearize(system, q, qd, t, args, inputs, u)
    if is_concrete((q, qd, t, args)):
        if bool(rank_deficient):
            raise _raise_rank("state")
        return lin
    checked = compiled_check(
        lin.state_matrix,
        rank_deficient,
        0,
        ("jaxlag.analysis.linearize: redundant constraints (rank-deficient Jacobian).",),
    )
    return eqx.tree_at(lambda x: x.state_matrix, lin, checked)


class _HeldInput(eqx.Module):
    """A control law that returns a fixed input (its value is a leaf: differentiable)."""

    value: Array

    def __call__(self, q, qd):
        return self.value


def _holding(system, u):
    """``system`` with its input held at ``u`` (the open loop)."""
    held = UserFunction(_HeldInput(u), (), "held input")
    return eqx.tree_at(lambda s: s.control, system, held, is_leaf=lambda x: x is None)


# Run once per state: compiled for its compile time (`jaxlag._compile.lean_jit`; the bicycle's
# 25,000-line program: 18.8 → 8.0 s of XLA time).
@compilation.lean_jit
def _linearize(system, q, qd, t, args, inputs, u):
    n = q.shape[0]
    actuated = system.actuation is not None

    def law(z, a):
        return _mechanics.control_input(system, z[:n], z[n:], t, a)

    def field(z, a, w):
        x, v = z[:n], z[n:]
        held = _holding(system, w) if actuated else system
        return jnp.concatenate([v, _accelerations(held, x, v, t, a)])

    y = jnp.concatenate([q, qd])
    u0 = (law(y, args) if u is None else u) if actuated else None
    state_matrix = jax.jacfwd(field)(y, args, u0)
    input_matrix, feedback_matrix = None, None
    if inputs is not None:
        if actuated and u is None:
            input_matrix = _input_derivative(lambda a: field(y, a, law(y, a)), args, inputs)
        else:
            input_matrix = _input_derivative(lambda a: field(y, a, u0), args, inputs)
    elif u0 is not None:
        shape = u0.shape
        input_matrix = jax.jacfwd(lambda w: field(y, args, w.reshape(shape)))(jnp.atleast_1d(u0))
        if system.control is not None:
            feedback_matrix = jax.jacfwd(lambda z: jnp.atleast_1d(law(z, args)))(y)
    constraint_jacobian = jax.jacfwd(lambda z: _state_constraints(system, z[:n], z[n:], t, args))(y)
    rank_deficient = _constraint_rank_check(constraint_jacobian)
    basis = tangent_basis(constraint_jacobian)
    left = _left_inverse(basis)
    reduced = left @ state_matrix @ basis
    reduced_input = None if input_matrix is None else left @ input_matrix
    return (
        Linearization(
            q, qd, t, state_matrix, input_matrix, basis, reduced, reduced_input, u0, feedback_matrix
        ),
        rank_deficient,
    )


class NormalModes(eqx.Module):
    """Small oscillations about an equilibrium at rest: ``K v = ω² M v`` on ``null(J)``.

    - ``frequencies_squared`` (d,): ``ω²`` ascending; negative values are unstable directions.
    - ``shapes`` (n, d): mode shapes in the coordinates ``q``, ``M``-orthonormal
      (``shapesᵀ M shapes = I``) and tangent to the constraints (``J shapes = 0``).
    - ``mass_matrix``, ``stiffness_matrix``: ``M_T`` and ``K_T`` in the basis ``basis`` (n × d)
      of ``null(J)``.
    """

    frequencies_squared: Float[Array, " d"]
    shapes: Float[Array, "n d"]
    mass_matrix: Float[Array, "d d"]
    stiffness_matrix: Float[Array, "d d"]
    basis: Float[Array, "n d"]

    @property
    def frequencies(self) -> Float[Array, " d"]:
        """``sign(ω²)·√|ω²|``: angular frequencies, or minus the growth rate of an unstable mode."""
        w2 = self.frequencies_squared
        return jnp.sign(w2) * jnp.sqrt(jnp.abs(w2))

    def is_stable(self, tolerance: float = 1e-10) -> Bool[Array, ""]:
        """Every ``ω² > tol·max|ω²|`` (Lagrange–Dirichlet), as a boolean array."""
        w2 = self.frequencies_squared
        return jnp.all(w2 > tolerance * jnp.max(jnp.abs(w2), initial=0.0))


def normal_modes(
    system: System, q: Coordinates, t: RealScalarLike = 0.0, args: Args = None, *, tolerance: float = 1e-6
) -> NormalModes:
    r"""Normal modes of small oscillations about an equilibrium ``q`` at rest (``q̇ = 0``).

    Solves ``K_T v = ω² M_T v`` on the tangent space of the holonomic constraints (see the
    module docstring). ``q`` must be an equilibrium: ``|q̈(q, 0)|`` is checked against
    ``tolerance`` times the size of the cancelling terms. Systems with velocity constraints, or
    steady motions (``q̇ ≠ 0``, gyroscopic terms), need `linearize` instead.

    Differentiable (``jax.grad`` of a frequency with respect to ``args``) and ``jit``-able.
    """
    q = jnp.asarray(q)
    if not jnp.issubdtype(q.dtype, jnp.floating):
        q = q.astype(jnp.result_type(float))
    qd = jnp.zeros_like(q)
    args = as_array_leaves(args, q.dtype)  # new parameter values must not recompile
    system.check(q, qd, t, args)
    if system.velocity_constraints is not None:
        raise ValueError(
            "normal_modes handles holonomic constraints only; for velocity (nonholonomic) "
            "constraints use jaxlag.analysis.linearize, whose spectrum is taken on the full "
            "constraint manifold."
        )
    t = jnp.asarray(t, q.dtype)
    modes, qdd, rank_deficient, not_equilibrium = _normal_modes(system, q, t, args, tolerance)
    if is_concrete((q, t, args)):
        if bool(rank_deficient):
            raise _raise_rank("holonomic")
        if bool(not_equilibrium):
            raise ValueError(
                f"normal_modes: q = {np.asarray(q)} is not an equilibrium at rest (q̈ = "
                f"{np.asarray(qdd)}). Find one first with jaxlag.analysis.equilibrium, or use "
                "jaxlag.analysis.linearize for a steady motion."
            )
        return modes
    w2 = compiled_check(
        modes.frequencies_squared,
        rank_deficient | not_equilibrium,
        jnp.where(rank_deficient, 0, 1),
        (
            "jaxlag.analysis.normal_modes: redundant constraints.",
            "jaxlag.analysis.normal_modes: q is not an equilibrium at rest (q̈ ≠ 0).",
        ),
    )
    return eqx.tree_at(lambda x: x.frequencies_squared, modes, w2)


@compilation.filter_jit
def _normal_modes(system, q, t, args, tolerance):
    qd = jnp.zeros_like(q)
    qdd = _accelerations(system, q, qd, t, args)
    stiffness_full = jax.jacfwd(lambda x: _accelerations(system, x, qd, t, args))(q)
    mass, force = _mechanics.mass_and_forces(system, q, qd, t, args)
    if system.holonomic is not None:
        jac = jax.jacfwd(lambda x: _constraints.holonomic_residual(system, x, t, args))(q)
    else:
        jac = jnp.zeros((0, q.shape[0]), q.dtype)
    rank_deficient = _constraint_rank_check(jac)
    scale = jnp.max(jnp.abs(jnp.linalg.solve(mass, force)), initial=0.0)
    not_equilibrium = ~(jnp.max(jnp.abs(qdd), initial=0.0) <= tolerance * (1.0 + scale))
    basis = tangent_basis(jac)
    mass_t = basis.T @ mass @ basis
    stiffness_t = -basis.T @ mass @ stiffness_full @ basis
    stiffness_t = 0.5 * (stiffness_t + stiffness_t.T)
    chol = jnp.linalg.cholesky(mass_t)
    inv_chol = jax.scipy.linalg.solve_triangular(chol, jnp.eye(chol.shape[0], dtype=q.dtype), lower=True)
    w2, vectors = jnp.linalg.eigh(inv_chol @ stiffness_t @ inv_chol.T)
    shapes = basis @ (inv_chol.T @ vectors)
    return NormalModes(w2, shapes, mass_t, stiffness_t, basis), qdd, rank_deficient, not_equilibrium
