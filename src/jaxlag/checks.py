"""Run-time checks of the initial state: loud, specific errors instead of silent NaNs.

When the inputs are concrete (``simulate`` called outside ``jit``/``vmap``) the checks run
eagerly and raise ``ValueError`` with the numbers and the offending constraints. Under a
transformation they become ``eqx.error_if`` checks compiled into the program, so bad input
still stops the computation.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from . import constraints as _constraints
from .kkt import accelerations_and_multipliers
from .mechanics import mass_matrix

#: A mass matrix whose smallest eigenvalue is below this fraction of its largest is singular.
MASS_RCOND = 1e-12
#: Constraint rows whose smallest singular value is below this fraction of the largest are
#: linearly dependent (redundant or conflicting constraints).
CONSTRAINT_RCOND = 1e-10


def _is_concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


def initial_activity(system, q, t, args, tolerance):
    """Holonomic activity mask at the start: unilateral constraints act only where ``f_i ≈ 0``."""
    if system.holonomic is None:
        return jnp.zeros((0,), bool)
    f = _constraints.holonomic_residual(system, q, t, args)
    active = jnp.ones(f.shape, bool)
    for i in system.unilateral:
        active = active.at[i].set(jnp.abs(f[i]) <= tolerance)
    return active


@eqx.filter_jit
def _diagnostics(system, q, qd, t, args, tolerance):
    """``(values, failures)`` at the initial state, in one compiled call (one host transfer)."""
    values = _diagnostic_values(system, q, qd, t, args, tolerance)
    return values, _failures(values, system.least_squares, tolerance)


def _diagnostic_values(system, q, qd, t, args, tolerance):
    system.check(q, qd, t, args)
    mass = mass_matrix(system, q, qd, t, args)
    eigenvalues = jnp.linalg.eigvalsh(mass)
    f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    active = initial_activity(system, q, t, args, tolerance)
    unilateral = jnp.zeros(f.shape, bool)
    for i in system.unilateral:
        unilateral = unilateral.at[i].set(True)
    row_weight = jnp.concatenate([active, jnp.ones(g.shape, bool)]).astype(q.dtype)
    if rows.shape[0] > 0:
        singular_values = jnp.linalg.svd(rows * row_weight[:, None], compute_uv=False)
    else:
        singular_values = jnp.ones((1,), q.dtype)
    if system.unilateral:
        _, lam, _ = accelerations_and_multipliers(system, q, qd, t, args, active=active)
        scale = 1.0 + jnp.max(jnp.abs(lam))
        wrong_sign = jnp.any(active & unilateral & (lam < -tolerance * scale))
    else:
        wrong_sign = jnp.asarray(False)
    off_diagonal = mass - jnp.diag(jnp.diagonal(mass))
    not_diagonal = system.diagonal_mass & ~(
        jnp.max(jnp.abs(off_diagonal)) <= 1e-12 * jnp.max(jnp.abs(mass))
    )
    return dict(
        finite=jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd)),
        not_diagonal=not_diagonal,
        mass=mass,
        eigenvalues=eigenvalues,
        f=jnp.where(active, f, 0.0),
        f_dot=jnp.where(active, f_dot, 0.0),
        f_raw=f,
        g=g,
        rows=rows * row_weight[:, None],
        num_active=jnp.sum(row_weight),
        singular_values=singular_values,
        violated=jnp.any(unilateral & (f < -tolerance)),
        wrong_sign=wrong_sign,
    )


def _failures(d, least_squares: bool, tolerance: float):
    eig = d["eigenvalues"]
    sv = d["singular_values"]
    residual = jnp.concatenate([jnp.abs(d["f"]), jnp.abs(d["f_dot"]), jnp.abs(d["g"]),
                                jnp.zeros((1,), eig.dtype)])
    rank = jnp.sum(sv > CONSTRAINT_RCOND * sv[0])
    return dict(
        nonfinite=~d["finite"],
        not_diagonal=d["not_diagonal"],
        mass=~(eig[0] > MASS_RCOND * jnp.max(jnp.abs(eig))),
        rank=jnp.asarray(False)
        if least_squares or d["rows"].shape[0] == 0
        else rank < d["num_active"],
        off_manifold=~(jnp.max(residual) <= tolerance),
        violated=d["violated"],
        wrong_sign=d["wrong_sign"],
    )


def _dependent_rows(rows: np.ndarray, m_h: int) -> list[str]:
    """Name each constraint row that is a linear combination of the rows before it."""
    found, kept = [], []
    for i in range(rows.shape[0]):
        candidate = np.array(kept + [rows[i]])
        sv = np.linalg.svd(candidate, compute_uv=False)
        rank = int(np.sum(sv > CONSTRAINT_RCOND * max(sv[0], 1e-300)))
        if rank == candidate.shape[0]:
            kept.append(rows[i])
        else:
            name = f"holonomic[{i}]" if i < m_h else f"velocity[{i - m_h}]"
            found.append(name)
    return found


_POINTER = (
    "Use jl.consistent_initial_state(system, q0, qd0, t0, args) to project an approximate "
    "initial state onto the constraint manifold."
)


def validate_initial_state(system, q, qd, t, args, tolerance: float):
    """Check the initial state; return ``(q, qd)`` (threaded through the run-time checks)."""
    d, fail = _diagnostics(system, q, qd, t, args, tolerance)
    # Concrete inputs can still give traced flags: a user function may close over a traced value.
    if _is_concrete((q, qd, t, args, fail)):
        fail = jax.device_get(fail)  # one transfer; the values are fetched only to report
        if not any(bool(x) for x in fail.values()):
            return q, qd
        if bool(fail["nonfinite"]):
            raise ValueError(f"The initial state is not finite: q0={np.asarray(q)}, qd0={np.asarray(qd)}.")
        if bool(fail["mass"]):
            raise ValueError(
                "The mass matrix M = ∂²L/∂q̇² is singular or not positive definite at the initial "
                f"state (eigenvalues {np.asarray(d['eigenvalues'])}). The Lagrangian is degenerate: "
                "every coordinate needs a kinetic term with a positive coefficient."
            )
        if bool(fail["not_diagonal"]):
            raise ValueError(
                "The system declares diagonal_mass=True, but M = ∂²L/∂q̇² has off-diagonal "
                f"entries at the initial state:\n{np.asarray(d['mass'])}"
            )
        if bool(fail["rank"]):
            m_h = d["f"].shape[0]
            names = _dependent_rows(np.asarray(d["rows"]), m_h)
            raise ValueError(
                "The constraints are redundant or conflicting at the initial state: the constraint "
                f"Jacobian [J; A] (singular values {np.asarray(d['singular_values'])}) is rank "
                f"deficient; dependent rows: {', '.join(names)}. Remove them, or pass "
                "least_squares=True to jl.System to accept consistent redundant constraints "
                "(minimum-norm multipliers)."
            )
        if bool(fail["violated"]):
            raise ValueError(
                f"A unilateral constraint is violated at the initial state (f_i < 0): f(q0) = "
                f"{np.asarray(d['f_raw'])}, unilateral indices {system.unilateral}. One-sided "
                "constraints are written f_i(q, t) >= 0."
            )
        if bool(fail["off_manifold"]):
            raise ValueError(
                "The initial state is off the constraint manifold beyond the tolerance "
                f"{tolerance:g}: f(q0) = {np.asarray(d['f'])}, ḟ = J q̇0 + ∂f/∂t = "
                f"{np.asarray(d['f_dot'])}, velocity constraints g = {np.asarray(d['g'])}. "
                + _POINTER
            )
        if bool(fail["wrong_sign"]):
            raise ValueError(
                "A unilateral constraint in contact at t0 has a multiplier of the wrong sign: it "
                "would have to pull (λ_i < 0) to hold, so it cannot be in contact. Start the motion "
                f"off the constraint (f_i > 0) instead. f(q0) = {np.asarray(d['f_raw'])}."
            )
        return q, qd
    q = eqx.error_if(q, fail["nonfinite"], "jaxlag: the initial state is not finite.")
    q = eqx.error_if(
        q,
        fail["mass"],
        "jaxlag: the mass matrix M = ∂²L/∂q̇² is singular or not positive definite at the "
        "initial state (degenerate Lagrangian).",
    )
    q = eqx.error_if(
        q,
        fail["not_diagonal"],
        "jaxlag: the system declares diagonal_mass=True, but M has off-diagonal entries.",
    )
    q = eqx.error_if(
        q,
        fail["rank"],
        "jaxlag: the constraints are redundant or conflicting at the initial state (rank-deficient "
        "constraint Jacobian). Call simulate outside jit to see which rows, or pass "
        "least_squares=True to jl.System.",
    )
    q = eqx.error_if(
        q,
        fail["off_manifold"],
        "jaxlag: the initial state is off the constraint manifold beyond tolerance. " + _POINTER,
    )
    q = eqx.error_if(
        q, fail["violated"], "jaxlag: a unilateral constraint is violated at the initial state."
    )
    q = eqx.error_if(
        q,
        fail["wrong_sign"],
        "jaxlag: a unilateral constraint in contact at t0 has a multiplier of the wrong sign "
        "(it would have to pull).",
    )
    return q, qd
