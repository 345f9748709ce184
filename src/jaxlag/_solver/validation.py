"""Which solver and step-size controller may be combined: one check for every entry point.

An adaptive step-size controller (``diffrax.PIDController``, also inside
``diffrax.ClipStepSizeController``) chooses each step from the solver's local error estimate.
diffrax marks the solvers that return one by ``diffrax.AbstractAdaptiveSolver`` (its own
``PIDController`` raises at trace time when a step returns no error, ``y_error is None``:
``diffrax.Euler``, ``SemiImplicitEuler``, ``LeapfrogMidpoint``, the Milstein methods, ...).
An explicit Runge–Kutta solver is always marked adaptive, but its error is
``h Σ b̂ᵢ kᵢ`` with the tableau's ``b_error``: when every ``b̂ᵢ`` is zero ([`jaxlag.RK4`][jaxlag.RK4],
which has no embedded method) the estimate is identically 0, the controller accepts every step
and grows it by ``factormax`` (×10) each time. Over ``[0, 10]`` a harmonic oscillator then takes
4 steps and ends 196 away from ``cos t`` with no error raised. `check_solver_controller`
refuses both combinations before anything is traced; ``jl.simulate``, ``jl.simulate_batch``
(``jl.Vmap()`` and ``jl.Ensemble()``) and ``jl.fit`` (through ``simulate``) all call it.

``diffrax.HalfSolver`` gives any solver an error estimate (by step doubling), so
``HalfSolver(jl.RK4())`` with a ``PIDController`` is accepted.
"""

import diffrax
import numpy as np


def _unwrapped(solver):
    """The solver that computes the step: through diffrax's ``AbstractWrappedSolver`` (which
    forwards ``isinstance``) and jaxlag's forwarding wrappers, but not through
    ``diffrax.HalfSolver``, which adds an error estimate of its own."""
    while not issubclass(type(solver), diffrax.HalfSolver):
        inner = getattr(solver, "solver", None)
        if not isinstance(inner, diffrax.AbstractSolver):
            break
        solver = inner
    return solver


def missing_error_estimate(solver) -> str | None:
    """Why ``solver`` gives no usable local error estimate, or ``None`` when it gives one."""
    solver = _unwrapped(solver)
    if issubclass(type(solver), diffrax.HalfSolver):
        return None
    name = type(solver).__name__
    if not isinstance(solver, diffrax.AbstractAdaptiveSolver):
        return f"{name} returns no local error estimate (it is not a diffrax.AbstractAdaptiveSolver)"
    tableau = getattr(solver, "tableau", None)
    tableaus = getattr(tableau, "tableaus", (tableau,))  # diffrax.MultiButcherTableau: several
    butcher = [t for t in tableaus if isinstance(t, diffrax.ButcherTableau)]
    if tableau is not None and len(butcher) == len(tableaus):
        if not any(np.any(np.asarray(t.b_error) != 0) for t in butcher):
            return (
                f"{name} has no embedded method (every b_error entry of its Butcher tableau is "
                "zero), so its error estimate is always 0"
            )
    return None


def _inner_controller(controller):
    """Through wrappers that hold the deciding controller (``diffrax.ClipStepSizeController``,
    jaxlag's guards): the controller that chooses the steps."""
    while True:
        inner = getattr(controller, "controller", None)
        if not isinstance(inner, diffrax.AbstractStepSizeController):
            return controller
        controller = inner


def is_adaptive(controller) -> bool:
    """Whether ``controller`` chooses steps from the solver's error estimate (diffrax's
    ``AbstractAdaptiveStepSizeController``); ``ConstantStepSize`` and ``StepTo`` do not."""
    return isinstance(_inner_controller(controller), diffrax.AbstractAdaptiveStepSizeController)


def solver_controller_message(solver, controller, *, default_controller: bool = False) -> str | None:
    """Why ``solver`` cannot be used with ``controller``, with what to pass instead, or ``None``.
    ``default_controller``: the user gave no ``stepsize_controller`` (the message says so)."""
    if not is_adaptive(controller):
        return None
    reason = missing_error_estimate(solver)
    if reason is None:
        return None
    name = type(_unwrapped(solver)).__name__
    given = "the default, " if default_controller else ""
    given += f"{type(_inner_controller(controller)).__name__}"
    return (
        f"solver={name}() cannot be used with an adaptive step-size controller (here {given}): "
        f"{reason}. The controller would "
        "accept every step and grow it without control of the error. Pass "
        "stepsize_controller=diffrax.ConstantStepSize() with a step dt0=..., or a solver with "
        f"an error estimate, such as diffrax.Tsit5() (or diffrax.HalfSolver({name}()), which "
        "estimates the error by step doubling)."
    )


def check_solver_controller(solver, controller, *, default_controller: bool = False) -> None:
    """Raise ``ValueError`` (see `solver_controller_message`) for a solver without an
    error estimate under an adaptive step-size controller. Static: runs before any tracing."""
    text = solver_controller_message(solver, controller, default_controller=default_controller)
    if text is not None:
        raise ValueError(text)
