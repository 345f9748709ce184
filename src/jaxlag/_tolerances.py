"""Thresholds shared by the checks and the failure diagnosis: rank tests and default tolerances."""

import jax.numpy as jnp

#: A mass matrix whose smallest eigenvalue is below this fraction of its largest is singular
#: (float64; lower precisions use ``rcond(dtype)``).
MASS_RCOND = 1e-12
#: Constraint rows whose smallest singular value is below this fraction of the largest are
#: linearly dependent (redundant or conflicting constraints).
CONSTRAINT_RCOND = 1e-10


def rcond(value: float, dtype) -> float:
    """A float64 rank threshold scaled to ``dtype``: at least 100 ulps (1.2e-5 in float32)."""
    return max(value, 100 * float(jnp.finfo(dtype).eps))


def default_constraint_tolerance(dtype) -> float:
    """``|f|, |ḟ|, |g|`` accepted at the initial state: 1e-8 in float64; in lower precision
    ``√ε`` of the dtype (3.5e-4 in float32), where round-off of ``f`` alone is ~1e-7·|q|²."""
    eps = float(jnp.finfo(dtype).eps)
    return 1e-8 if eps <= float(jnp.finfo(jnp.float64).eps) else eps**0.5


def default_solver_tolerance(dtype) -> float:
    """``rtol = atol`` of the default ``PIDController``: 1e-10 in float64, 100 ulps otherwise
    (1.2e-5 in float32: tighter tolerances than round-off stall the step-size control)."""
    eps = float(jnp.finfo(dtype).eps)
    return 1e-10 if eps <= float(jnp.finfo(jnp.float64).eps) else 100 * eps
