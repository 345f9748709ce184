r"""The two optimisation loops of [`fit`][jaxlag.fit], one function each, minimizing
``ℓ(y) = ½ |r(y)|²`` over the free variables ``y``.

* `least_squares_loop`: an optimistix Gauss–Newton-type solver (``optx.LevenbergMarquardt``,
  ``optx.GaussNewton``, ``optx.Dogleg``, ``optx.IndirectLevenbergMarquardt``), stepped on the
  linearization ``r + J (y − y₀)`` at each trial point ``y₀`` (one compiled program gives ``r``
  and ``J``, a small one the step), through the solver's public ``init``/``step``/``terminate``.
* `optax_loop`: an ``optax.GradientTransformation`` on ``∇ℓ`` from ``jax.value_and_grad``
  through the simulation.
"""

from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import optimistix as optx
from jax.flatten_util import ravel_pytree

from .. import _compile as compilation
from .._adjoint import ForwardSensitivities
from .model import Linearization, Linearizer, Problem


class Search(eqx.Module):
    """Where a loop ended: the free variables ``free``, ``history`` (``ℓ`` after each step, index 0
    at the start), ``num_steps``, ``converged``, the last linearization (None for optax) and
    which program linearized last (`Linearizer.lean`; None for optax)."""

    free: dict[str, Any]
    history: list[float]
    num_steps: int
    converged: bool
    linearization: Linearization | None
    lean: bool | None = None


def least_squares_loop(
    solver: optx.AbstractGaussNewton, problem: Problem, max_steps: int, progress: bool
) -> Search:
    """Step ``solver`` on the linearization at each trial point until it terminates.

    optimistix' Gauss–Newton step evaluates the residual function only at its trial point ``y₀``
    and linearizes it there; the linear model ``r + J (y − y₀)`` with ``r``, ``J`` taken at ``y₀``
    has the same value and Jacobian there, so the step is the one the solver takes on the
    simulation itself. The step also returns the next trial point (see `_ls_step`).
    The loss after each step is ``½ |r|²`` at the point the solver returns: the trial point when
    it accepted it, else the last accepted point.
    """
    free, trial, history, converged, steps = problem.free, problem.free, [], False, 0
    linearize = Linearizer(problem.model, problem.data, problem.fixed_states, free)
    linearization = linearize(free)
    state = _ls_init(solver, free, linearization)
    loss = float(0.5 * np.sum(np.asarray(linearization.residuals) ** 2))
    if max_steps < 1:
        history.append(loss)
    with _progress_bar(max_steps, progress) as bar:
        for steps in range(1, max_steps + 1):
            if steps > 1:
                linearization = linearize(trial)
            free, state, trial, done, accepted, trial_loss = _ls_step(solver, free, state, linearization)
            done, accepted, trial_loss = jax.device_get((done, accepted, trial_loss))
            loss = float(trial_loss) if accepted else loss
            if steps == 1:  # the first step evaluates the starting point and stays there
                history.append(loss)
            history.append(loss)
            bar.update(1)
            bar.set_postfix(loss=loss)
            if bool(done):
                converged = True
                break
    return Search(free, _finite(history), steps, converged, linearization, linearize.lean)


def optax_loop(
    optimizer: optax.GradientTransformation, problem: Problem, max_steps: int, progress: bool
) -> Search:
    """``max_steps`` updates of ``optimizer`` with ``∇ℓ``; ``converged`` is always True."""
    model, data, fixed_states = problem.model, problem.data, problem.fixed_states
    free, history, steps = problem.free, [], 0
    opt_state = optimizer.init(free)
    with _progress_bar(max_steps, progress) as bar:
        for steps in range(1, max_steps + 1):
            value, grads = _value_and_grad(model, free, data, fixed_states)
            history.append(float(value))
            free, opt_state = _optax_update(optimizer, free, opt_state, grads)
            bar.update(1)
            bar.set_postfix(loss=history[-1])
    history.append(float(_value_and_grad(model, free, data, fixed_states)[0]))
    return Search(free, _finite(history), steps, True, None)


def _finite(history: list[float]) -> list[float]:
    if not np.isfinite(history[-1]):
        raise FloatingPointError(
            "The fit diverged (non-finite loss): start closer, bound the "
            "parameters with `transforms`, or lower the learning rate."
        )
    return history


def _linear_model(free, linearization: Linearization):
    """``r + J (y − y₀)``: the residuals linearized at ``y₀``."""
    y = ravel_pytree(free)[0]
    return linearization.residuals + linearization.jacobian @ (y - linearization.point), None


def _probe(free, linearization: Linearization):
    """Zero residuals with the Jacobian ``J``: ``J (y − stop_gradient(y))``. No loss is below
    zero, so every search accepts the point it evaluates this at: a step on it returns the trial
    point it was given."""
    y = ravel_pytree(free)[0]
    return linearization.jacobian @ (y - jax.lax.stop_gradient(y)), None


@compilation.lean_jit
def _ls_init(solver, free, linearization):
    f_struct, aux_struct = jax.eval_shape(_linear_model, free, linearization)
    return solver.init(_linear_model, free, linearization, {}, f_struct, aux_struct, frozenset())


@compilation.lean_jit
def _ls_step(solver, free, state, linearization: Linearization):
    """One optimistix step on the linearization at its trial point, in one program.

    Returns the point the solver moved to, its state, the next trial point, whether to stop,
    whether the solver accepted the trial point (it then returns that point) and ``½ |r|²``
    there. The next trial point comes from the solver's public interface alone: a second step
    from the new state on `_probe` (discarded but for the point it returns) is accepted.
    """
    free, state, _ = solver.step(_linear_model, free, linearization, {}, state, frozenset())
    done, _ = solver.terminate(_linear_model, free, linearization, {}, state, frozenset())
    trial, _, _ = solver.step(_probe, free, linearization, {}, state, frozenset())
    y = ravel_pytree(free)[0]
    accepted = jnp.array_equal(y, linearization.point)
    # At the optimum the actual reduction is rounding noise and trial steps can be rejected
    # (the trust region then shrinks the step 4x per step, up to ~16 more steps): a rejected
    # trial whose next step is already within the solver's y tolerance ends the fit, as further
    # steps could not move the parameters by more than that tolerance.
    step = ravel_pytree(trial)[0] - y
    within = solver.norm(jnp.abs(step) / (solver.atol + solver.rtol * jnp.abs(y))) < 1
    done = done | (within & ~accepted)
    loss = 0.5 * jnp.sum(linearization.residuals**2)
    return free, state, trial, done, accepted, loss


@compilation.filter_jit
def _value_and_grad(model, free, data, fixed_states):
    # The default adjoint: forward sensitivities for up to 10 free scalars, else checkpointed.
    adjoint = ForwardSensitivities()
    return jax.value_and_grad(lambda f: 0.5 * jnp.sum(model.residuals(f, data, fixed_states, adjoint) ** 2))(
        free
    )


@compilation.filter_jit
def _optax_update(optimizer, free, opt_state, grads):
    updates, opt_state = optimizer.update(grads, opt_state, free)
    return optax.apply_updates(free, updates), opt_state


class _NoProgressBar:
    """``progress=False``: a progress bar that shows nothing."""

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False

    def update(self, n: int) -> None:
        pass

    def set_postfix(self, **values) -> None:
        pass


def _progress_bar(total: int, enabled: bool) -> Any:
    if not enabled:
        return _NoProgressBar()
    try:
        from tqdm.auto import tqdm
    except ImportError as error:  # pragma: no cover - depends on the environment
        raise ImportError("progress=True needs tqdm: pip install tqdm") from error
    return tqdm(total=total, desc="jaxlag.fit")
