"""Constant steps (``diffrax.ConstantStepSize()`` and ``dt0``) as XLA loops.

Save interval ``k`` of member ``b`` is divided into ``m = ceil((t_{k+1} − t_k)/dt0)`` equal
steps, so the last step lands exactly on the save time (the steps are ``dt0`` wherever ``dt0``
divides the intervals). The loop is a ``lax.scan`` over save intervals around a ``lax.scan`` over
steps whose body is ``jax.checkpoint``-ed: forward mode (``jax.jvp``/``jacfwd``) differentiates it
directly, reverse mode stores one state per step and recomputes the stages.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .step import constant_step

__all__ = ["constant_grid", "constant_loop"]


def constant_grid(ts: np.ndarray, dt0: float):
    """Steps per save interval: ``m[b, k] = ceil((t_{k+1} − t_k)/dt0)`` (round-off tolerant).

    ``ts`` (B, T) concrete. Returns ``m`` (B, T−1) int and the static inner length ``max m``.
    """
    intervals = np.diff(ts, axis=1)
    ratio = intervals / dt0
    m = np.ceil(ratio - 1e-9 * np.maximum(1.0, ratio)).astype(np.int64)
    m = np.maximum(m, 1)
    return m, int(m.max()) if m.size else 0


def step_counts(steps_per_interval):
    """The loop statistics of constant steps: ``steps_per_interval`` (B, T−1) summed per member."""
    counts = jnp.sum(jnp.asarray(steps_per_interval, jnp.int32), axis=1, dtype=jnp.int32)
    return {"num_steps": counts, "num_accepted_steps": counts, "num_rejected_steps": jnp.zeros_like(counts)}


def constant_loop(field, settings, ts, y0, steps_per_interval, inner, uniform):
    """Constant steps: scan over save intervals, inner scan over the steps of each interval.

    Returns the saved states ``(q, q̇)`` each (T−1, B, n), the statistics and an all-true mask."""
    tableau = settings.tableau
    m = jnp.asarray(steps_per_interval, jnp.int32).T  # (T-1, B)
    starts = ts[:, :-1].T  # (T-1, B)
    h_all = jnp.diff(ts, axis=1).T / m.astype(ts.dtype)

    @jax.checkpoint
    def step(carry, j, t_start, h, m_k):
        t = t_start + j.astype(h.dtype) * h
        t1 = jnp.where(j + 1 == m_k, t_start + m_k.astype(h.dtype) * h, t + h)
        return constant_step(field, tableau, t, h, t1, carry, None if uniform else j < m_k), None

    def interval(carry, xs):
        t_start, h, m_k = xs
        carry, _ = jax.lax.scan(
            lambda c, j: step(c, j, t_start, h, m_k), carry, jnp.arange(inner, dtype=jnp.int32)
        )
        return carry, carry[0]

    f0 = field(ts[:, 0], y0) if tableau.fsal else None
    _, saved = jax.lax.scan(interval, (y0, f0), (starts, h_all, m))
    stats = step_counts(steps_per_interval)
    return saved, stats, jnp.ones(stats["num_steps"].shape, bool)
