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
from .mechanics import mass_matrix

#: A mass matrix whose smallest eigenvalue is below this fraction of its largest is singular.
MASS_RCOND = 1e-12
#: Constraint rows whose smallest singular value is below this fraction of the largest are
#: linearly dependent (redundant or conflicting constraints).
CONSTRAINT_RCOND = 1e-10


def _is_concrete(tree) -> bool:
    return not any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves(tree))


@eqx.filter_jit
def _diagnostics(system, q, qd, t, args):
    system.check(q, qd, t, args)
    mass = mass_matrix(system, q, qd, t, args)
    eigenvalues = jnp.linalg.eigvalsh(mass)
    f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    if rows.shape[0] > 0:
        singular_values = jnp.linalg.svd(rows, compute_uv=False)
    else:
        singular_values = jnp.ones((1,), q.dtype)
    return dict(
        finite=jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd)),
        eigenvalues=eigenvalues,
        f=f,
        f_dot=f_dot,
        g=g,
        rows=rows,
        singular_values=singular_values,
    )


def _failures(d, least_squares: bool, tolerance: float):
    eig = d["eigenvalues"]
    sv = d["singular_values"]
    residual = jnp.concatenate([jnp.abs(d["f"]), jnp.abs(d["f_dot"]), jnp.abs(d["g"]),
                                jnp.zeros((1,), eig.dtype)])
    return dict(
        nonfinite=~d["finite"],
        mass=~(eig[0] > MASS_RCOND * jnp.max(jnp.abs(eig))),
        rank=jnp.asarray(False)
        if least_squares
        else jnp.asarray(d["rows"].shape[0] > d["rows"].shape[1]) | ~(sv[-1] > CONSTRAINT_RCOND * sv[0]),
        off_manifold=~(jnp.max(residual) <= tolerance),
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
    d = _diagnostics(system, q, qd, t, args)
    fail = _failures(d, system.least_squares, tolerance)
    if _is_concrete((q, qd, t, args)):
        if bool(fail["nonfinite"]):
            raise ValueError(f"The initial state is not finite: q0={np.asarray(q)}, qd0={np.asarray(qd)}.")
        if bool(fail["mass"]):
            raise ValueError(
                "The mass matrix M = ∂²L/∂q̇² is singular or not positive definite at the initial "
                f"state (eigenvalues {np.asarray(d['eigenvalues'])}). The Lagrangian is degenerate: "
                "every coordinate needs a kinetic term with a positive coefficient."
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
        if bool(fail["off_manifold"]):
            raise ValueError(
                "The initial state is off the constraint manifold beyond the tolerance "
                f"{tolerance:g}: f(q0) = {np.asarray(d['f'])}, ḟ = J q̇0 + ∂f/∂t = "
                f"{np.asarray(d['f_dot'])}, velocity constraints g = {np.asarray(d['g'])}. "
                + _POINTER
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
    return q, qd
