"""What the ensemble loop needs to know about the diffrax objects it was given, decided before
tracing: the Butcher tableau of the solver, the step-size controller's constants and the loop
kind of the adjoint (`make_settings`). Anything the loop cannot do is refused here, with the
option to use instead."""

from typing import Any

import diffrax
import equinox as eqx
import numpy as np
import optimistix as optx

from ..._custom_types import RealScalarLike
from ..._solver.validation import solver_controller_message

__all__ = ["Tableau", "EnsembleSettings", "tableau_of", "make_settings"]


def tableau_of(solver) -> diffrax.ButcherTableau:
    """The explicit Butcher tableau of a diffrax solver, or a clear error."""
    tableau = solver.tableau if isinstance(solver, diffrax.AbstractRungeKutta) else None
    if isinstance(solver, diffrax.AbstractWrappedSolver) or not isinstance(tableau, diffrax.ButcherTableau):
        raise TypeError(
            f"The ensemble integrator needs an explicit Runge–Kutta solver with a Butcher tableau "
            f"(diffrax.Tsit5(), diffrax.Dopri5(), jl.RK4(), ...); {type(solver).__name__} has none. "
            "Use simulate_batch(..., method=jl.Vmap()) for any other diffrax solver."
        )
    if tableau.a_diagonal is not None and np.any(np.asarray(tableau.a_diagonal) != 0):
        raise TypeError(
            f"{type(solver).__name__} is implicit (its tableau has a diagonal); the ensemble "
            "integrator is explicit only. Use simulate_batch(..., method=jl.Vmap())."
        )
    return tableau


class Tableau(eqx.Module):
    """A Butcher tableau as tuples of floats (hashable: it is static in the compiled program)."""

    c: tuple[float, ...] = eqx.field(static=True)
    a_lower: tuple[tuple[float, ...], ...] = eqx.field(static=True)
    b_sol: tuple[float, ...] = eqx.field(static=True)
    b_error: tuple[float, ...] = eqx.field(static=True)
    fsal: bool = eqx.field(static=True)

    @classmethod
    def from_diffrax(cls, tableau: diffrax.ButcherTableau) -> "Tableau":
        def floats(x):
            return tuple(float(v) for v in np.asarray(x))

        return cls(
            floats(tableau.c),
            tuple(floats(a) for a in tableau.a_lower),
            floats(tableau.b_sol),
            floats(tableau.b_error),
            bool(tableau.fsal),
        )


class EnsembleSettings(eqx.Module):
    """What the loop needs to know, decided before tracing (all static except the tolerances)."""

    tableau: Tableau = eqx.field(static=True)
    adaptive: bool = eqx.field(static=True)
    error_order: float = eqx.field(static=True)
    rtol: RealScalarLike | None = None
    atol: RealScalarLike | None = None
    pcoeff: float = eqx.field(static=True, default=0.0)
    icoeff: float = eqx.field(static=True, default=1.0)
    dcoeff: float = eqx.field(static=True, default=0.0)
    safety: float = eqx.field(static=True, default=0.9)
    factormin: float = eqx.field(static=True, default=0.2)
    factormax: float = eqx.field(static=True, default=10.0)
    dtmin: RealScalarLike | None = None
    dtmax: RealScalarLike | None = None
    max_steps: int = eqx.field(static=True, default=2**16)
    loop_kind: str = eqx.field(static=True, default="checkpointed")
    throw: bool = eqx.field(static=True, default=True)  # not read by the loop: see member_failures


def _static_float(value, name):
    if isinstance(value, (int, float, np.floating, np.integer)):
        return float(value)
    try:
        return float(np.asarray(value))
    except Exception:  # noqa: BLE001
        raise TypeError(
            f"PIDController.{name} must be a concrete number for the ensemble integrator; got {value!r}."
        ) from None


def _loop_kind(adjoint) -> str:
    """The ``equinox.internal.while_loop`` kind of the adaptive loop, as diffrax picks it."""
    if adjoint is None or isinstance(adjoint, diffrax.RecursiveCheckpointAdjoint):
        return "checkpointed"
    if isinstance(adjoint, diffrax.ForwardMode):
        return "lax"
    raise TypeError(
        "adjoint must be diffrax.RecursiveCheckpointAdjoint() (reverse mode, the default) or "
        f"diffrax.ForwardMode() (forward mode) for the ensemble integrator; got {adjoint!r}."
    )


def _check_controller(solver, controller) -> None:
    """A ``PIDController`` the loop reproduces exactly, or an error naming what it lacks."""
    if type(controller) is not diffrax.PIDController:
        raise TypeError(
            "stepsize_controller must be diffrax.ConstantStepSize() or diffrax.PIDController(...) "
            f"for the ensemble integrator; got {type(controller).__name__}. Use "
            "simulate_batch(..., method=jl.Vmap())."
        )
    text = solver_controller_message(solver, controller)
    if text is not None:
        raise ValueError(text)
    if controller.norm is not optx.rms_norm:
        raise ValueError(
            "The ensemble integrator uses diffrax's default RMS error norm; a custom "
            "PIDController.norm is not supported (use method=jl.Vmap())."
        )
    if not controller.force_dtmin:
        raise ValueError(
            "PIDController(force_dtmin=False) is not supported by the ensemble "
            "integrator (use method=jl.Vmap())."
        )


def _pid_settings(solver, controller: diffrax.PIDController, common: dict[str, Any]) -> EnsembleSettings:
    error_order = controller.error_order
    if error_order is None:
        error_order = solver.error_order(diffrax.ODETerm(lambda t, y, a: y))
    return EnsembleSettings(
        adaptive=True,
        error_order=_static_float(error_order, "error_order"),
        rtol=controller.rtol,
        atol=controller.atol,
        pcoeff=_static_float(controller.pcoeff, "pcoeff"),
        icoeff=_static_float(controller.icoeff, "icoeff"),
        dcoeff=_static_float(controller.dcoeff, "dcoeff"),
        safety=_static_float(controller.safety, "safety"),
        factormin=_static_float(controller.factormin, "factormin"),
        factormax=_static_float(controller.factormax, "factormax"),
        dtmin=controller.dtmin,
        dtmax=controller.dtmax,
        **common,
    )


def make_settings(solver, stepsize_controller, max_steps, adjoint, throw) -> EnsembleSettings:
    """Validate the diffrax objects and turn them into `EnsembleSettings`."""
    tableau = tableau_of(solver)
    if max_steps is None or int(max_steps) < 1:
        raise ValueError(
            f"max_steps must be a positive integer for the ensemble integrator; got {max_steps!r}."
        )
    kind = _loop_kind(adjoint)
    common: dict[str, Any] = dict(
        tableau=Tableau.from_diffrax(tableau), max_steps=int(max_steps), loop_kind=kind, throw=bool(throw)
    )
    if isinstance(stepsize_controller, diffrax.ConstantStepSize):
        return EnsembleSettings(adaptive=False, error_order=0.0, **common)
    _check_controller(solver, stepsize_controller)
    return _pid_settings(solver, stepsize_controller, common)
