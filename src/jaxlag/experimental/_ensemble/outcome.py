"""How each member ended: the loop's `LoopRecord` turned into the `Failure` record and diffrax
result of ``jl.simulate``, with the saves a member did not reach set to ``inf`` (diffrax's and
``jl.Vmap()``'s convention). Works for every backend: besides the adaptive loop's record, it reads
the saves only."""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Int

from ... import _errors as failures
from ..._errors import FailureCode

__all__ = ["LoopRecord", "member_failures"]


class LoopRecord(eqx.Module):
    """How the adaptive loop ended for each member (leading axis B): ``code`` (the results
    enumeration of `jaxlag._errors`), ``reached`` (save columns written, start excluded),
    ``t`` (time reached), ``dt`` (last step tried) and ``q``, ``qd`` (last accepted state)."""

    code: Int[Array, " batch"]
    reached: Int[Array, " batch"]
    t: Float[Array, " batch"]
    dt: Float[Array, " batch"]
    q: Float[Array, "batch n"]
    qd: Float[Array, "batch n"]


def _result_of(code):
    """The diffrax result of one member (the guard of ``jl.simulate`` reports a non-finite
    or collapsed step as ``dt_min_reached``)."""
    results = diffrax.RESULTS
    stopped = results.where(code == FailureCode.MAX_STEPS, results.max_steps_reached, results.dt_min_reached)
    return results.where(code == FailureCode.COMPLETED, results.successful, stopped)


def _constant_record(ts, saved, steps_per_interval):
    """Constant steps reach every save: the record of a completed run, and the steps (B, T−1)."""
    q_saved, qd_saved = saved
    intervals, batch = q_saved.shape[:2]
    h = jnp.diff(ts, axis=1) / jnp.asarray(steps_per_interval, ts.dtype)  # (B, T-1)
    record = LoopRecord(
        jnp.full((batch,), FailureCode.COMPLETED, jnp.int32),
        jnp.full((batch,), intervals, jnp.int32),
        ts[:, -1],
        h[:, -1],
        q_saved[-1],
        qd_saved[-1],
    )
    return record, h


def _stopped_at_nonfinite_saves(ts, y0, saved, record: LoopRecord, h) -> LoopRecord:
    """A member that completed with a non-finite save failed there (code 1): reported at its
    last finite save (``t``, ``q``, ``q̇`` there; ``dt`` the step of the interval that blew up,
    from ``h`` (B, T−1) for constant steps, else the last step tried)."""
    saved = jax.lax.stop_gradient(saved)
    intervals, batch = saved[0].shape[:2]
    members = jnp.arange(batch)
    column = jnp.arange(intervals, dtype=record.reached.dtype)[:, None]  # (T-1, 1)
    finite = jnp.all(jnp.isfinite(saved[0]), axis=-1) & jnp.all(jnp.isfinite(saved[1]), axis=-1)
    bad = ~finite & (column < record.reached[None, :])  # (T-1, B)
    first = jnp.argmax(bad, axis=0).astype(record.reached.dtype)
    late = (record.code == FailureCode.COMPLETED) & jnp.any(bad, axis=0)
    before = jnp.maximum(first - 1, 0)

    def last_good(saves, start):
        return jnp.where((first > 0)[:, None], saves[before, members], start)

    y0 = jax.lax.stop_gradient(y0)
    dt_late = record.dt if h is None else h[members, first]
    return LoopRecord(
        jnp.where(late, FailureCode.NONFINITE, record.code),
        jnp.where(late, first, record.reached),
        jnp.where(late, ts[members, first], record.t),
        jnp.where(late, dt_late, record.dt),
        jnp.where(late[:, None], last_good(saved[0], y0[0]), record.q),
        jnp.where(late[:, None], last_good(saved[1], y0[1]), record.qd),
    )


def member_failures(ts, y0, saved, stats, record, steps_per_interval, max_steps):
    """Each member's `Failure` record, its diffrax result and its saves
    with the unreached ones set to ``inf``.

    ``saved`` (q, q̇) each (T−1, B, n); ``record`` the adaptive loop's `LoopRecord`, or
    ``None`` for constant steps (every save is reached), with ``steps_per_interval`` (B, T−1).
    Either way a member whose saved state is non-finite failed there (code 1, non-finite): a
    constant step cannot be shrunk, and the Pallas kernel and the constant-step loop do not stop
    a member whose state became NaN."""
    h = None
    if record is None:
        record, h = _constant_record(ts, saved, steps_per_interval)
    record = _stopped_at_nonfinite_saves(ts, y0, saved, record, h)
    column = jnp.arange(saved[0].shape[0], dtype=record.reached.dtype)[:, None]  # (T-1, 1)
    unreached = (column >= record.reached[None, :])[:, :, None]
    q_out, qd_out = (jnp.where(unreached, jnp.inf, x) for x in saved)
    result = jax.vmap(_result_of)(record.code)
    failure = failures.Failure(
        code=record.code,
        t=record.t,
        dt=record.dt,
        q=record.q,
        qd=record.qd,
        t0=ts[:, 0],
        t1=ts[:, -1],
        num_steps=jnp.asarray(stats["num_steps"], jnp.int32),
        result=jnp.asarray(result._value, jnp.int32),
        max_steps=max_steps,
    )
    return (q_out, qd_out), failure, result
