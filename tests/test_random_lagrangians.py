r"""Hypothesis sweep over random Lagrangians: jaxlag's accelerations and multipliers solve the
constrained equations of motion to round-off, or a clear error is raised; never a silent NaN.

Family (n = 3, everything random, time-dependent, rheonomic constraints):

    L(q, q̇, t) = ½ q̇ᵀ M(q) q̇ + c(q, t)·q̇ − V(q, t)
    M(q) = A  or  A + B·diag(sin² q)          A = R Rᵀ + δ I, δ ∈ [1e-3, 1], B ≥ 0 (SPD)
    c(q, t) = C sin(q) cos(w t)                (gyroscopic / moving-frame terms)
    V(q, t) = ½ qᵀK q + p·q³ + a·cos(W q + φ) + e t q₀
    f(q, t) = R_f q + S_f sin(q) + u (q·q) + s sin(w_f t)          0, 1 or 2 rows
    g(q, q̇, t) = (a₀ + a₁ cos q)·q̇ + b sin(t + q₀)               0 or 1 row

The reference quantities are computed here with plain JAX, independently of jaxlag: ``M`` by
``jax.hessian``, ``F = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t`` by ``jacfwd``, and the constraint
equations as derivatives along the motion itself: ``J q̈ + γ = d²/ds² f(q + s q̇ + ½ s² q̈, t + s)``
at ``s = 0`` (nested ``jvp``) and ``A q̈ + (∂g/∂q) q̇ + ∂g/∂t = d/ds g(q + s q̇, q̇ + s q̈, t + s)``.
So the test checks ``M q̈ = F + Jᵀλ + Aᵀμ``, ``J q̈ = −γ`` and the velocity-constraint equation
for jaxlag's ``q̈``, ``λ``, ``μ`` (``System.accelerations``, ``multipliers``,
``velocity_multipliers``, called under ``jax.jit`` and ``jax.vmap``).

Tolerance. jaxlag solves the KKT system in range-space form (Cholesky of M, then of the Schur
complement ``S = G M⁻¹ Gᵀ``). Each Cholesky solve is backward stable, so the residuals are
bounded by a modest multiple of ``eps·κ(M)`` times the size of the terms involved: the KKT matrix
times the solution ``‖[[M, Gᵀ], [G, 0]]‖·‖(q̈, Λ)‖`` plus the magnitudes of the terms summed into
``F`` and into ``γ`` (their own round-off, here and in jaxlag, since the two evaluations of the
same formula need not round alike). ``TOLERANCE_FACTOR = 10`` is 30× the largest ratio
residual / (eps·κ(M)·scale) measured, 0.34, over 9600 random states (200 seeds × the 12 structures
× 4 states, κ(A) up to 2.4e3).

Degenerate systems: redundant constraint rows are accepted with ``least_squares=True`` (the same
equations hold with the minimum-norm multipliers; the tolerance gains a factor κ_r(G)², and the
largest measured ratio is 0.36 over 6000 states with 3 rows of rank 2) and are otherwise rejected
by ``jl.simulate`` with a message naming the dependent rows; a singular mass matrix is rejected by
``jl.simulate`` with its eigenvalues. The ``System`` methods at a state do not check either case
(they return NaN): see ``test_system_methods_at_a_degenerate_state_raise``.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

import jaxlag as jl

jax.config.update("jax_enable_x64", True)

N = 3
EPS = float(np.finfo(np.float64).eps)
TOLERANCE_FACTOR = 10.0
STATES_PER_EXAMPLE = 4


def _mass(q, args, state_dependent):
    if state_dependent:
        return args["A"] + jnp.diag(args["B"] * jnp.sin(q) ** 2)
    return args["A"]


def _lagrangian(q, qd, t, args, state_dependent):
    mass = _mass(q, args, state_dependent)
    coupling = args["C"] @ jnp.sin(q) * jnp.cos(args["w"] * t)
    potential = (
        0.5 * q @ args["K"] @ q
        + args["p"] @ q**3
        + args["a"] @ jnp.cos(args["W"] @ q + args["phi"])
        + args["e"] * t * q[0]
    )
    return 0.5 * qd @ mass @ qd + coupling @ qd - potential


def _holonomic(q, t, args):
    return (
        args["Rf"] @ q + args["Sf"] @ jnp.sin(q) + args["u"] * (q @ q) + args["s"] * jnp.sin(args["wf"] * t)
    )


def _velocity(q, qd, t, args):
    return jnp.reshape((args["a0"] + args["a1"] * jnp.cos(q)) @ qd + args["b"] * jnp.sin(t + q[0]), (1,))


def _redundant(q, t, args):
    """The random rows followed by a combination of them: a rank-deficient Jacobian everywhere."""
    f = _holonomic(q, t, args)
    return jnp.concatenate([f, (args["combination"] @ f)[None]])


def _functions(state_dependent, holonomic_rows, velocity_rows, redundant=False):
    """``(L, f or None, g or None)`` of one structure, as named functions of (q, [qd], t, args)."""

    def lagrangian(q, qd, t, args):
        return _lagrangian(q, qd, t, args, state_dependent)

    holonomic = (_redundant if redundant else _holonomic) if holonomic_rows else None
    return lagrangian, holonomic, _velocity if velocity_rows else None


def random_args(rng, holonomic_rows, velocity_rows):
    factor = rng.uniform(-1.0, 1.0, (N, N))
    stiffness = rng.uniform(-1.0, 1.0, (N, N))
    return {
        "A": factor @ factor.T + 10.0 ** rng.uniform(-3.0, 0.0) * np.eye(N),  # κ(A) up to ~10³
        "B": rng.uniform(0.0, 2.0, N),
        "C": rng.uniform(-1.0, 1.0, (N, N)),
        "w": rng.uniform(0.5, 3.0),
        "K": stiffness + stiffness.T,
        "p": rng.uniform(-0.5, 0.5, N),
        "a": rng.uniform(-2.0, 2.0, N),
        "W": rng.uniform(-2.0, 2.0, (N, N)),
        "phi": rng.uniform(0.0, 2 * np.pi, N),
        "e": rng.uniform(-1.0, 1.0),
        "Rf": rng.uniform(-1.0, 1.0, (holonomic_rows, N)),
        "Sf": rng.uniform(-1.0, 1.0, (holonomic_rows, N)),
        "u": rng.uniform(-0.5, 0.5, holonomic_rows),
        "s": rng.uniform(-0.5, 0.5, holonomic_rows),
        "wf": rng.uniform(0.5, 3.0),
        "a0": rng.uniform(-1.0, 1.0, N),
        "a1": rng.uniform(-0.5, 0.5, N),
        "b": rng.uniform(-1.0, 1.0),
        "combination": rng.uniform(-2.0, 2.0, holonomic_rows),
    }


def _reference_residuals(lagrangian, holonomic, velocity, q, qd, t, args, qdd, lam, mu, redundant=False):
    """The equations of motion evaluated here, by plain JAX, at jaxlag's (q̈, λ, μ).

    ``lagrangian(q, qd, t, args)``, ``holonomic(q, t, args)`` and ``velocity(q, qd, t, args)``
    (either may be None). Returns ``(dynamics residual, constraint residual, tolerance)``.
    ``redundant``: the rows are rank deficient (least squares); the minimum-norm solve then also
    loses accuracy with the conditioning of the Schur complement on its range, ≲ κ_r(G)² κ(M),
    where κ_r(G) = σ₁/σ_r over the non-zero singular values (here rank r = m − 1).
    """
    momenta = jax.grad(lagrangian, argnums=1)
    mass = jax.hessian(lagrangian, argnums=1)(q, qd, t, args)
    force_terms = [
        jax.grad(lagrangian, argnums=0)(q, qd, t, args),
        -jax.jacfwd(momenta, argnums=0)(q, qd, t, args) @ qd,
        -jax.jacfwd(momenta, argnums=2)(q, qd, t, args),
    ]
    force = sum(force_terms)

    rows, constraint_residuals, curvature_terms = [], [], []
    if holonomic is not None:

        def along_motion(s):  # f on the curve q + s q̇ + ½ s² q̈: its 2nd derivative is J q̈ + γ
            return holonomic(q + s * qd + 0.5 * s**2 * qdd, t + s, args)

        def along_free(s):  # f along q + s q̇ alone: its 2nd derivative is γ
            return holonomic(q + s * qd, t + s, args)

        def second_derivative(path):
            return jax.jvp(lambda s: jax.jvp(path, (s,), (1.0,))[1], (0.0,), (1.0,))[1]

        jacobian = jax.jacfwd(holonomic)(q, t, args)
        rows.append(jacobian)
        constraint_residuals.append(second_derivative(along_motion))
        curvature_terms.append(second_derivative(along_free))
    if velocity is not None:
        a_matrix = jax.jacfwd(velocity, argnums=1)(q, qd, t, args)
        rows.append(a_matrix)
        constraint_residuals.append(
            jax.jvp(lambda s: velocity(q + s * qd, qd + s * qdd, t + s, args), (0.0,), (1.0,))[1]
        )
        # A q̈ + (∂g/∂q) q̇ + ∂g/∂t: the last two terms' size
        curvature_terms.append(jax.jvp(lambda s: velocity(q + s * qd, qd, t + s, args), (0.0,), (1.0,))[1])
    multipliers = jnp.concatenate([lam, mu])
    if rows:
        constraint_rows = jnp.concatenate(rows, axis=0)
        dynamics = mass @ qdd - force - constraint_rows.T @ multipliers
        constraint = jnp.concatenate(constraint_residuals)
        row_singular_values = jnp.linalg.svd(constraint_rows, compute_uv=False)
        row_norm = row_singular_values[0]
        if redundant:
            rank = constraint_rows.shape[0] - 1
            range_condition = row_singular_values[0] / row_singular_values[rank - 1]
        curvature = jnp.linalg.norm(jnp.concatenate(curvature_terms))
    else:
        dynamics, constraint = mass @ qdd - force, jnp.zeros(0)
        row_norm = curvature = 0.0

    singular_values = jnp.linalg.svd(mass, compute_uv=False)
    condition = singular_values[0] / singular_values[-1]
    kkt_norm = singular_values[0] + 2 * row_norm  # ≥ ‖[[M, Gᵀ], [G, 0]]‖
    solution = jnp.linalg.norm(qdd) + jnp.linalg.norm(multipliers)
    terms = sum(jnp.linalg.norm(term) for term in force_terms) + curvature
    tolerance = TOLERANCE_FACTOR * EPS * condition * (kkt_norm * solution + terms)
    if redundant:
        tolerance = tolerance * range_condition**2
    return dynamics, constraint, tolerance


_EVALUATORS = {}
_SYSTEMS = {}


def system_of(state_dependent, holonomic_rows, velocity_rows, redundant=False, least_squares=False):
    """The jl.System of one structure, built once (so its compiled functions are reused)."""
    key = (state_dependent, holonomic_rows, velocity_rows, redundant, least_squares)
    if key not in _SYSTEMS:
        functions = _functions(*key[:4])
        _SYSTEMS[key] = (
            jl.System(
                functions[0],
                holonomic=functions[1],
                velocity_constraints=functions[2],
                least_squares=least_squares,
            ),
            functions,
        )
    return _SYSTEMS[key]


def evaluator(state_dependent, holonomic_rows, velocity_rows, redundant=False):
    """One compiled function per structure, shared by every example that draws it:
    jaxlag's q̈, λ, μ for a batch of states (``jax.vmap`` under ``jax.jit``) and the residuals.
    ``redundant``: the holonomic rows are followed by a combination of them, and the system is
    built with ``least_squares=True``."""
    key = (state_dependent, holonomic_rows, velocity_rows, redundant)
    if key not in _EVALUATORS:
        system, functions = system_of(*key, least_squares=redundant)

        def one(q, qd, t, args):
            qdd = system.accelerations(q, qd, t, args)
            lam = system.multipliers(q, qd, t, args)
            mu = system.velocity_multipliers(q, qd, t, args)
            return (qdd, lam, mu) + _reference_residuals(
                *functions, q, qd, t, args, qdd, lam, mu, redundant=redundant
            )

        _EVALUATORS[key] = jax.jit(jax.vmap(one, in_axes=(0, 0, 0, None)))
    return _EVALUATORS[key]


@settings(max_examples=40, deadline=None)
@given(
    state_dependent=st.booleans(),
    holonomic_rows=st.integers(0, 2),
    velocity_rows=st.integers(0, 1),
    seed=st.integers(0, 2**32 - 1),
)
def test_accelerations_and_multipliers_solve_the_constrained_equations(
    state_dependent, holonomic_rows, velocity_rows, seed
):
    rng = np.random.default_rng(seed)
    args = random_args(rng, holonomic_rows, velocity_rows)
    q = rng.uniform(-1.5, 1.5, (STATES_PER_EXAMPLE, N))
    qd = rng.uniform(-2.0, 2.0, (STATES_PER_EXAMPLE, N))
    t = rng.uniform(0.0, 5.0, STATES_PER_EXAMPLE)
    qdd, lam, mu, dynamics, constraint, tolerance = evaluator(state_dependent, holonomic_rows, velocity_rows)(
        q, qd, t, args
    )
    assert qdd.shape == (STATES_PER_EXAMPLE, N)
    assert lam.shape == (STATES_PER_EXAMPLE, holonomic_rows)
    assert mu.shape == (STATES_PER_EXAMPLE, velocity_rows)
    for name, value in (("q̈", qdd), ("λ", lam), ("μ", mu), ("tolerance", tolerance)):
        assert np.all(np.isfinite(value)), (name, value)
    for k in range(STATES_PER_EXAMPLE):
        assert np.max(np.abs(dynamics[k]), initial=0.0) <= tolerance[k], (k, dynamics[k], tolerance[k])
        assert np.max(np.abs(constraint[k]), initial=0.0) <= tolerance[k], (k, constraint[k], tolerance[k])


@settings(max_examples=10, deadline=None)
@given(holonomic_rows=st.integers(1, 2), seed=st.integers(0, 2**32 - 1))
def test_redundant_rows_with_least_squares_solve_the_same_equations(holonomic_rows, seed):
    # f = (f₁, …, f_m, c·f): consistent, so q̈ is unique and Jᵀλ (λ minimum-norm) too.
    rng = np.random.default_rng(seed)
    args = random_args(rng, holonomic_rows, 0)
    q = rng.uniform(-1.5, 1.5, (STATES_PER_EXAMPLE, N))
    qd = rng.uniform(-2.0, 2.0, (STATES_PER_EXAMPLE, N))
    t = rng.uniform(0.0, 5.0, STATES_PER_EXAMPLE)
    qdd, lam, mu, dynamics, constraint, tolerance = evaluator(True, holonomic_rows, 0, True)(q, qd, t, args)
    assert lam.shape == (STATES_PER_EXAMPLE, holonomic_rows + 1)
    for name, value in (("q̈", qdd), ("λ", lam), ("tolerance", tolerance)):
        assert np.all(np.isfinite(value)), (name, value)
    for k in range(STATES_PER_EXAMPLE):
        assert np.max(np.abs(dynamics[k])) <= tolerance[k], (k, dynamics[k], tolerance[k])
        assert np.max(np.abs(constraint[k])) <= tolerance[k], (k, constraint[k], tolerance[k])


@settings(max_examples=8, deadline=None)
@given(holonomic_rows=st.integers(1, 2), seed=st.integers(0, 2**32 - 1))
def test_redundant_rows_are_rejected_by_simulate_naming_the_row(holonomic_rows, seed):
    rng = np.random.default_rng(seed)
    args = random_args(rng, holonomic_rows, 0)
    system, _ = system_of(True, holonomic_rows, 0, redundant=True)
    q, qd = rng.uniform(-1.5, 1.5, N), rng.uniform(-2.0, 2.0, N)
    with pytest.raises(ValueError, match=rf"redundant.*dependent rows: holonomic\[{holonomic_rows}\]"):
        jl.simulate(system, q, qd, jnp.linspace(0.0, 0.1, 3), args=args)


@settings(max_examples=8, deadline=None)
@given(state_dependent=st.booleans(), seed=st.integers(0, 2**32 - 1))
def test_a_singular_mass_matrix_is_rejected_by_simulate(state_dependent, seed):
    # A = R Rᵀ with R of rank 2: singular; with B·diag(sin² q) at q = 0, M(0) = A.
    rng = np.random.default_rng(seed)
    args = random_args(rng, 0, 0)
    factor = rng.uniform(-1.0, 1.0, (N, 2))
    args["A"] = factor @ factor.T
    system, _ = system_of(state_dependent, 0, 0)
    q = np.zeros(N) if state_dependent else rng.uniform(-1.5, 1.5, N)
    with pytest.raises(ValueError, match="mass matrix .* singular"):
        jl.simulate(system, q, rng.uniform(-2.0, 2.0, N), jnp.linspace(0.0, 0.1, 3), args=args)


@pytest.mark.parametrize("case", ["singular mass matrix", "redundant rows"])
def test_system_methods_at_a_degenerate_state_raise(case):
    rng = np.random.default_rng(0)
    if case == "singular mass matrix":
        args = random_args(rng, 0, 0)
        factor = rng.uniform(-1.0, 1.0, (N, 2))
        args["A"] = factor @ factor.T
        system, _ = system_of(False, 0, 0)
    else:
        args = random_args(rng, 1, 0)
        system, _ = system_of(True, 1, 0, redundant=True)
    q, qd = rng.uniform(-1.5, 1.5, N), rng.uniform(-2.0, 2.0, N)
    match = "singular or not positive definite" if case == "singular mass matrix" else "redundant"
    with pytest.raises(ValueError, match=match):
        system.accelerations(q, qd, 0.0, args)
    with pytest.raises(Exception, match=match):  # compiled: the same message from the program
        jax.block_until_ready(jax.jit(lambda q: system.accelerations(q, qd, 0.0, args))(q))
