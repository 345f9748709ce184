r"""The eager diagnosis of a failed simulation: the host-side message, with the numbers.

A compiled program raises only the static `message` of its
failure. Called eagerly (concrete inputs), `raise_if_failed` fetches the
`Failure` record and builds the full message here: where and when the run
stopped, the state, and for the failing state a diagnosis by small compiled probes (which
quantity is non-finite: ``L``, ``M``, ``F``, constraints or accelerations; the eigenvalues of
``M``; a discontinuity of ``q̈`` that the state is stuck at, or a fast mode that holds the steps
small; how many steps or segments would be needed). For a batch, the first failing member.
"""

from typing import NamedTuple

import diffrax
import jax
import jax.numpy as jnp
import numpy as np

from . import _compile as compilation
from ._batch_members import batch_prefix, failed_members, member
from ._checks import validate_initial_state
from ._errors import Failure, FailureCode, SimulationError
from ._mechanics import constraints as _constraints
from ._mechanics.kkt import accelerations_and_multipliers
from ._mechanics.lagrangian import (
    actuation_forces,
    control_input,
    mass_matrix,
    unconstrained_accelerations,
)
from ._solver.guard import _ULPS
from ._tolerances import MASS_RCOND, rcond


# ----------------------------------------------------------------------------- probes
@compilation.filter_jit
def _probe(system, q, qd, t, dt, args):
    """Which quantity is non-finite at ``(q, q̇, t)`` and one Euler step of size ``dt`` later."""

    def at(q, qd, t):
        finite = lambda x: jnp.all(jnp.isfinite(x))  # noqa: E731
        L = system.lagrangian(q, qd, t=t, args=args)
        M = mass_matrix(system, q, qd, t, args)
        if system.is_constrained:
            f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
            constraints_ok = finite(f) & finite(f_dot) & finite(g)
            qdd = accelerations_and_multipliers(system, q, qd, t, args)[0]
        else:
            constraints_ok = jnp.asarray(True)
            qdd = unconstrained_accelerations(system, q, qd, t, args)
        eig = jnp.linalg.eigvalsh(jnp.where(jnp.isfinite(M), M, 0.0))
        # Each of the user's force functions on its own, so that the one that returned NaN is
        # named (True for those the system does not have).
        yes = jnp.asarray(True)
        forces_ok = dissipation_ok = control_ok = actuation_ok = yes
        if system.forces is not None:
            forces_ok = finite(system.forces(q, qd, t=t, args=args))
        if system.dissipation is not None:
            dissipation_ok = finite(jax.grad(lambda v: system.dissipation(q, v, t=t, args=args))(qd))
        if system.actuation is not None and system.control is not None:
            u = control_input(system, q, qd, t, args)
            control_ok = finite(u)
            actuation_ok = finite(actuation_forces(system, q, qd, t, args, u=jnp.where(control_ok, u, 0.0)))
        flags = dict(
            state=finite(q) & finite(qd),
            lagrangian=finite(L),
            mass_matrix=finite(M),
            constraints=constraints_ok,
            forces=forces_ok,
            dissipation=dissipation_ok,
            control=control_ok,
            actuation=actuation_ok,
            accelerations=finite(qdd),
        )
        return flags, eig, qdd

    flags, eig, qdd = at(q, qd, t)
    step = jnp.where(jnp.isfinite(dt) & (dt > 0), dt, 0.0)
    q1 = q + step * qd
    qd1 = qd + step * jnp.where(jnp.isfinite(qdd), qdd, 0.0)
    flags1, eig1, _ = at(q1, qd1, t + step)
    return (flags, eig, qdd), (flags1, eig1, q1, qd1)


_CAUSES = {
    "state": "the state itself",
    "lagrangian": "the Lagrangian L",
    "mass_matrix": "the mass matrix M = ∂²L/∂q̇²",
    "constraints": "the constraint functions (f, ḟ or g)",
    "forces": "the force function Q(q, q̇, [t], [args]) (System(..., forces=...))",
    "dissipation": "the dissipation force −∂R/∂q̇ of the Rayleigh function (System(..., dissipation=...))",
    "control": "the control law's input u = control(q, q̇, [t], [args]) (System(..., control=...) "
    "or system.with_control(...))",
    "actuation": "the actuation Q_u(q, q̇, u, [t], [args]) of the control law's (finite) input u "
    "(System(..., actuation=...))",
    "accelerations": "the accelerations q̈ (L, M, the constraints and the user's forces are "
    "finite: a derivative of L or of the constraints is not, or the solve M q̈ = F + Jᵀλ failed)",
}


#: The quantities of `_CAUSES` that are a user's force function on its own.
_USER_FORCES = ("forces", "dissipation", "control", "actuation")


def _fmt(x) -> str:
    """An array for a message; long ones (a 100-link chain) by their ends and their size."""
    x = np.asarray(x)
    text = np.array2string(x, precision=6, separator=", ", max_line_width=200, threshold=12, edgeitems=3)
    return text if x.size <= 12 else f"{text} (n = {x.size})"


def _singular(eig) -> bool:
    """The initial-state check's criterion (``jaxlag._tolerances.MASS_RCOND``, scaled to the dtype)."""
    eig = np.asarray(eig)
    threshold = rcond(MASS_RCOND, eig.dtype) if eig.size else 0.0
    return bool(eig.size) and not eig[0] > threshold * max(np.max(np.abs(eig)), 1e-300)


def _x64_hint(dtype) -> str:
    if np.dtype(dtype) == np.float64:
        return ""
    if jax.dtypes.canonicalize_dtype(np.float64) == np.float64:  # x64 on: float32 passed on purpose
        return (
            f" (The simulation runs in {np.dtype(dtype).name}, the dtype of q0: mechanics in "
            "single precision keeps ~7 digits; pass float64 arrays for ~16.)"
        )
    return (
        f" (The simulation runs in {np.dtype(dtype).name}: jax_enable_x64 is off. Mechanics "
        "in single precision keeps ~7 digits; enable float64 with "
        "jax.config.update('jax_enable_x64', True) before creating arrays.)"
    )


def describe(failure: Failure, system=None, args=None, events=None) -> str:
    """The message for one (unbatched, concrete) failure record. ``events``: the run's
    [`Events`][jaxlag.Events], to name the reset of a failed one."""
    code = int(failure.code)
    t, dt = float(failure.t), float(failure.dt)
    t0, t1 = float(failure.t0), float(failure.t1)
    q, qd = np.asarray(failure.q), np.asarray(failure.qd)
    hint = _x64_hint(q.dtype)
    where = f"at t = {t:.10g} (interval [{t0:g}, {t1:g}])"
    state = f"q = {_fmt(q)}, q̇ = {_fmt(qd)}"
    # Stuck at a discontinuity, or held back by stiffness: what the failed run's last state shows
    # (evaluated only for the two codes where a step-size limit is the cause).
    cause = (
        _step_limit(system, failure, args)
        if code in (FailureCode.MAX_STEPS, FailureCode.STEP_SIZE_COLLAPSED) and system is not None
        else None
    )
    if code == FailureCode.MAX_STEPS:
        done = (t - t0) / (t1 - t0) if t1 != t0 else 0.0
        steps = int(failure.num_steps)
        msg = (
            f"The simulation reached max_steps = {failure.max_steps or steps} steps {where}, "
            f"{100 * done:.1f}% of the way"
        )
        if cause is not None and cause.kind == "discontinuity":
            return msg + f", with steps of dt = {dt:.3g} from {state}. " + cause.text + hint
        if done > 1e-3:
            needed = int(np.ceil(steps / done))
            suggestion = int(2 ** np.ceil(np.log2(needed * 1.2)))
            msg += (
                f": at this rate about {needed:,} steps are needed. Pass max_steps="
                f"{suggestion} (or more), or loosen the step-size controller's rtol/atol "
                "(default 1e-10), or use a constant step size."
            )
        else:
            msg += (
                f"; the last step size was {dt:.3g}. The steps are far too small for the "
                "interval: the system may be stiff or singular near this state "
                f"({state})."
            )
        if cause is not None:
            msg += " " + cause.text
        return msg + hint
    if code in (FailureCode.RESTITUTION, FailureCode.FRICTION_COEFFICIENT, FailureCode.RESET):
        return _parameter_or_reset_text(code, failure, system, args, events, where, state) + hint
    if code in (FailureCode.INITIAL_STATE, FailureCode.PARAMETER, FailureCode.SAVE_TIMES):
        return _refused_text(code, failure, system, args)
    if code == FailureCode.MAX_SEGMENTS:
        used = failure.max_segments
        done = (t - t0) / (t1 - t0) if t1 != t0 else 0.0
        msg = (
            f"The simulation needed more than max_segments = {used} segments (a segment ends at "
            "each release, contact and event, terminal or recorded, at each crossing that a "
            "condition's direction ignores, and at the end time): "
            f"after {used} it had reached t = {t:.10g}, {100 * done:.1f}% of [{t0:g}, {t1:g}]"
        )
        accumulation = _accumulation_text(failure, system)
        if accumulation is not None:
            return msg + accumulation
        if done > 1e-3 and used:
            needed = int(np.ceil(used / done)) + 1
            suggestion = int(2 ** np.ceil(np.log2(needed * 1.2)))
            return msg + (
                f"; at this rate about {needed} segments are needed. Pass "
                f"events=jl.Events(..., max_segments={suggestion}) (or more)."
            )
        return msg + (
            "; the switches pile up at one time (a contact that chatters, or a condition that "
            "keeps crossing zero there), so more segments would not help. Run with "
            "throw=False and look at traj.events to see which switch repeats."
        )
    if code == FailureCode.SOLVER:
        text = _result_text(int(failure.result))
        return f"The diffrax solver failed {where}: {text}" + hint
    if code == FailureCode.NONFINITE:
        msg = f"The equations of motion became non-finite (NaN or inf) {where}, from {state}"
        msg += f"; no step, down to dt = {dt:.3g}, gave a finite state." if np.isfinite(dt) else "."
    else:  # STEP_SIZE_COLLAPSED
        msg = (
            f"The step size collapsed to dt = {dt:.3g} {where}: every step from {state} was "
            "rejected although finite."
        )
        if cause is not None:
            return msg + " " + cause.text + hint
        msg += (
            " The solution appears to reach a singularity here (a velocity or acceleration "
            "blowing up, a mass matrix becoming singular)."
        )
    if system is not None:
        msg += " " + _diagnosis(system, failure, args)
    return msg + hint


# ----------------------------------------------------------------------------- step-size limits
def _accelerations(system, q, qd, t, args):
    if system.is_constrained:
        return accelerations_and_multipliers(system, q, qd, t, args)[0]
    return unconstrained_accelerations(system, q, qd, t, args)


@compilation.filter_jit
def _linearization(system, q, qd, t, args):
    """``ẏ`` and ``∂ẏ/∂y`` of the first-order system ``y = (q, q̇)``, ``ẏ = (q̇, q̈)``, and the
    screen of `_step_limit`: for each component ``y_j``, the change of ``q̈``
    across ``y_j ± δ_j`` (``δ_j = 10⁻² (1 + |y_j|)``) and what the derivative predicts for it."""
    n = q.shape[0]

    def field(y):
        return jnp.concatenate([y[n:], _accelerations(system, y[:n], y[n:], t, args)])

    y = jnp.concatenate([q, qd])
    ydot = field(y)
    jac = jax.jacfwd(field)(y)
    delta = 1e-2 * (1.0 + jnp.abs(y))
    shift = jnp.diag(delta)
    plus = jax.vmap(lambda e: field(y + e)[n:])(shift)
    minus = jax.vmap(lambda e: field(y - e)[n:])(shift)
    jump = jnp.linalg.norm(plus - minus, axis=-1)
    predicted = 2.0 * delta * jnp.linalg.norm(jnp.where(jnp.isfinite(jac[n:]), jac[n:], 0.0), axis=0)
    return ydot, jac, jump, predicted


@compilation.filter_jit
def _bisect(system, q, qd, t, args, j):
    """Locate where ``q̈`` jumps as component ``j`` of ``y = (q, q̇)`` moves through
    ``y_j ± δ_j`` (the interval of `_linearization`'s screen): bisection on the larger
    change. Returns the final bracket ``(a, b)`` and ``q̈`` at its ends; for a smooth ``q̈`` the
    change across the final bracket vanishes with its width, across a discontinuity it does not."""
    n = q.shape[0]
    y = jnp.concatenate([q, qd])

    def acc(x):
        z = y.at[j].set(x)
        return _accelerations(system, z[:n], z[n:], t, args)

    delta = 1e-2 * (1.0 + jnp.abs(y[j]))
    a, b = y[j] - delta, y[j] + delta

    def body(_, carry):
        a, b, fa, fb = carry
        m = 0.5 * (a + b)
        fm = acc(m)
        left = jnp.linalg.norm(fa - fm)
        right = jnp.linalg.norm(fm - fb)
        go_left = left >= right
        return (
            jnp.where(go_left, a, m),
            jnp.where(go_left, m, b),
            jnp.where(go_left, fa, fm),
            jnp.where(go_left, fm, fb),
        )

    return jax.lax.fori_loop(0, 80, body, (a, b, acc(a), acc(b)))


def _component(j: int, n: int) -> str:
    return f"q[{j}]" if j < n else f"q̇[{j - n}]"


class _Cause(NamedTuple):
    kind: str  # "discontinuity" or "stiffness"
    text: str


def _step_limit(system, failure: Failure, args) -> _Cause | None:
    """Why the steps stayed small, from the last state of the failed run: a discontinuity of
    ``q̈`` that the state is stuck at, or stiffness (a fast, stable mode far quicker than the
    motion). ``None`` if neither is found (or the equations cannot be evaluated there)."""
    q, qd, t, dt = failure.q, failure.qd, failure.t, float(failure.dt)
    try:
        ydot, jac, jump, predicted = jax.device_get(_linearization(system, q, qd, t, args))
    except Exception:  # noqa: BLE001 - the diagnosis must not hide the failure
        return None
    n = np.asarray(q).shape[0]
    dtype = np.asarray(q).dtype
    # A jump that does not shrink with the interval: screened by the derivative, then bisected.
    suspicious = np.isfinite(jump) & (jump > 10.0 * np.nan_to_num(predicted) + 1e-12)
    for j in np.argsort(-np.where(suspicious, jump, -np.inf))[: min(4, int(np.sum(suspicious)))]:
        try:
            a, b, fa, fb = jax.device_get(_bisect(system, q, qd, t, args, int(j)))
        except Exception:  # noqa: BLE001
            continue
        size = float(np.linalg.norm(fa - fb))
        width = float(b - a)
        if np.isfinite(size) and size >= 0.5 * float(jump[j]) and width <= 1e-6 * (1.0 + abs(float(a))):
            return _Cause("discontinuity", _discontinuity_text(j, n, a, b, fa, fb, q, qd, dt))
    if not (np.all(np.isfinite(jac)) and np.all(np.isfinite(ydot))):
        return None
    eig, vectors = np.linalg.eig(jac)
    k = int(np.argmax(np.abs(eig)))
    rho = float(np.abs(eig[k]))
    # A step rejected with ρ·dt of order one is a stability (or fast-mode) limit; towards a
    # finite-time singularity the steps shrink for accuracy with ρ·dt ≈ 0.05 instead.
    if not (np.isfinite(dt) and rho * dt >= 0.25):
        return None
    y = np.concatenate([np.asarray(q), np.asarray(qd)])
    floor = 1e-3 * max(1.0, float(np.max(np.abs(y))))
    rate = float(np.max(np.abs(ydot) / (np.abs(y) + floor)))
    lam = eig[k]
    oscillating = abs(lam.imag) > 1e-3 * abs(lam)
    slow = rho >= 30.0 * rate  # the state itself moves far slower than the fast mode
    t0, t1 = float(failure.t0), float(failure.t1)
    scale = max(abs(t0), abs(t1), abs(t1 - t0))
    resolution = _ULPS * float(np.finfo(dtype).eps) * scale
    limit = 3.0 / rho
    at_round_off = limit <= 4 * resolution
    if failure.code == FailureCode.MAX_STEPS and not (slow or at_round_off):
        return None  # a fast motion resolved accurately: more steps is the right advice
    mode = np.abs(vectors[:, k])
    members = [_component(int(i), n) for i in np.argsort(-mode)[:3] if mode[i] >= 0.3 * np.max(mode)]
    remaining = max(t1 - float(t), 0.0)
    steps = int(np.ceil(remaining / limit)) if remaining > 0 else 0
    if oscillating:
        value = f"{lam.real:.3g} ± {abs(lam.imag):.3g}i"
        kind = f"a fast oscillation, period 2π/|λ| = {2 * np.pi / rho:.2g}"
    else:
        value = f"{lam.real:.3g}"
        kind = "stiff" if lam.real < 0 else "a fast growth"
    opening = (
        "The steps are held small by a fast mode of the equations of motion"
        if failure.code == FailureCode.MAX_STEPS
        else "The equations of motion have a fast mode here, not a singularity"
    )
    text = (
        f"{opening}: the linearized "
        f"equations ∂(q̇, q̈)/∂(q, q̇) have an eigenvalue λ = {value} ({kind}; |λ| = {rho:.3g} "
        f"per unit time, its mode mostly in {', '.join(members)})"
    )
    if slow:
        text += f", while the state changes at a rate of only about {rate:.3g}"
    text += (
        f". An explicit solver needs steps below about 3/|λ| = {limit:.2g} to stay stable, "
        "whatever the accuracy asked for"
    )
    if at_round_off:
        text += (
            f", and in {np.dtype(dtype).name} that is at the round-off of t: the smallest step "
            f"resolved on this interval is {resolution:.2g}. M is regular and everything is "
            "finite."
        )
        if np.finfo(dtype).eps > np.finfo(np.float64).eps:
            text += (
                " Fix: enable float64 (jax.config.update('jax_enable_x64', True) before "
                f"creating arrays, and float64 q0), where such steps resolve (about {steps:,} of "
                "them for the rest of the interval: pass max_steps="
                f"{int(2 ** np.ceil(np.log2(max(steps, 1) * 1.2)))} or more), or remove the fast "
                "mode."
            )
        else:
            text += " Fix: remove the fast mode."
    else:
        text += (
            f" (about {steps:,} more steps to the end time): more steps will finish, or remove the fast mode."
        )
    return _Cause(
        "stiffness",
        text + " A rate this high comes from a very stiff spring or damper, a large gain or a "
        "tiny mass: make the stiff element a constraint, soften it, or rescale it.",
    )


def _discontinuity_text(j, n, a, b, fa, fb, q, qd, dt) -> str:
    y = np.concatenate([np.asarray(q), np.asarray(qd)])
    name = _component(int(j), n)
    at = 0.5 * (float(a) + float(b))
    if abs(at) <= 1e3 * (float(b) - float(a)) + 1e-300:
        at = 0.0  # at zero to the resolution of the bisection
    size = float(np.linalg.norm(fa - fb))
    worst = int(np.argmax(np.abs(fa - fb)))
    velocity = j >= n
    text = (
        f"The state is stuck at a discontinuity of the equations of motion: q̈ jumps by "
        f"{size:.3g} (q̈[{worst}] from {float(fa[worst]):.6g} to {float(fb[worst]):.6g}) where "
        f"{name} crosses {at:.3g}, and the run ended with {name} = {float(y[j]):.3g}, on it. "
        "No number of steps will finish it: each step crosses the jump and reverses "
        f"(chattering), so the steps stay at dt ≈ {dt:.2g} however many are allowed. "
    )
    if velocity:
        text += (
            "A force that switches with the sign of a velocity, like Coulomb friction "
            "−μN·sign(v), has no solution that moves off v = 0 while the other forces are "
            "below μN (the body sticks). Regularize it: −μN·tanh(v/ε), with ε a small velocity "
            "(e.g. 1e-3 of the typical speed). Consequences: sticking becomes a slow creep at "
            "|v| ≈ ε·artanh(F/μN) under a force F < μN, and the force's slope μN/ε makes the "
            "equations stiff (steps of about m·ε/(μN) with an explicit solver), so a smaller ε "
            "is more faithful and slower. Or, where the normal force is a constraint multiplier, "
            "use the stick–slip element: jl.System(..., friction=jl.Coulomb(contact, tangent, "
            "mu)) sticks exactly and switches at the closed-form times."
        )
    else:
        text += (
            "A force that switches with position (a step in a potential or force, a contact "
            "written with a sign or a comparison) has no classical solution that stays on it. "
            "Regularize the switch: a smooth ramp such as tanh(x/ε) of width ε (the smaller "
            "ε, the stiffer the equations and the smaller the steps), or split the motion into "
            "phases at the switch with jl.Event."
        )
    return text


def _optional_float(x) -> float | None:
    """A scalar of the record (``None`` for a record without that field)."""
    return None if x is None else float(np.asarray(x))


def _optional_int(x) -> int | None:
    return None if x is None else int(np.asarray(x))


def _suggestion(count: float) -> int:
    """A power of two above ``count`` with 20 % to spare."""
    return int(2 ** np.ceil(np.log2(max(count, 1.0) * 1.2)))


def _accumulation_text(failure: Failure, system) -> str | None:
    """The advice of ``MAX_SEGMENTS`` when the run stopped in an accumulation of impacts: the
    record's ``value`` is the number of segments by the geometric series of the flights
    (`jaxlag._mechanics.impacts.impacts_to_rest`); ``None`` if it is not one."""
    needed = _optional_float(failure.value)
    row = _optional_int(failure.index)
    if needed is None or not np.isfinite(needed) or row is None or row < 0:
        return None
    law = getattr(system, "unilateral_law", None) if system is not None else None
    restitution = ""
    if law is not None and row in law.indices:
        e = np.asarray(law.restitution)
        if e.ndim == 1 and e.size == len(law.indices):
            restitution = f" e = {float(e[law.indices.index(row)]):g}"
    text = (
        f"; the impacts on unilateral row {row} accumulate (a body bouncing to rest with "
        f"restitution{restitution}): the flights between them shrink geometrically, so the rate "
        "so far says little. By the geometric series of the flights the run needs about "
        f"{int(needed):,} segments in all. Pass events=jl.Events(..., "
        f"max_segments={_suggestion(needed)}) (or more), or end the accumulation sooner with a "
        "larger zeno_time: events=jl.Events(..., zeno_time=τ) makes an impact plastic (the "
        "contact persists) once its rebound would fly less than τ (the default ends it only "
        "when the rebound would rise less than the constraint tolerance)."
    )
    if needed > 10_000:
        text += f" {int(needed):,} segments take long to run: a larger zeno_time is the better lever."
    return text


def _parameter_or_reset_text(code, failure: Failure, system, args, events, where: str, state: str) -> str:
    """The eager messages of `FailureCode.RESTITUTION`, ``FRICTION_COEFFICIENT`` and ``RESET``,
    with the record's ``index`` and ``value``."""
    index = _optional_int(failure.index)
    value = _optional_float(failure.value)
    shown = "?" if value is None else f"{value:g}"
    traced = (
        " It came in traced (through jit, vmap or grad), so it could not be checked when the "
        "system was built; the simulation stopped before its first step."
    )
    if code == FailureCode.RESTITUTION:
        law = getattr(system, "unilateral_law", None) if system is not None else None
        row = ""
        if law is not None and index is not None and 0 <= index < len(law.indices):
            row = f" of unilateral row {law.indices[index]}"
        return (
            f"The coefficient of restitution{row} is restitution = {shown} "
            "(jl.Unilateral(..., restitution=e)): it must be a finite number in [0, 1] (0 "
            "plastic, 1 elastic). e > 1 adds energy at every impact (a ball would bounce higher "
            "each time), e < 0 lets the body pass into the constraint, and jax.grad would "
            "differentiate that motion as if it were physical." + traced
        )
    if code == FailureCode.FRICTION_COEFFICIENT:
        contact = ""
        elements = getattr(system, "friction", ()) if system is not None else ()
        if index is not None and 0 <= index < len(elements):
            contact = f" (on holonomic row {elements[index].contact})"
        return (
            f"The friction coefficient of Coulomb contact {index}{contact} is mu = {shown} "
            "(jl.Coulomb(contact, tangent, mu)): mu must be finite and >= 0. With mu < 0 the "
            "friction force drives the slip instead of opposing it (a block would be pushed up "
            "the slope by it)." + traced
        )
    name = ""
    output = ""
    conditions = getattr(events, "conditions", ())
    if index is not None and 0 <= index < len(conditions) and conditions[index].reset is not None:
        reset = conditions[index].reset
        fn = getattr(reset, "fn", reset)
        label = getattr(fn, "__qualname__", None)
        name = f" ({label if isinstance(label, str) else repr(fn)})"
        try:
            q_r, qd_r = reset(
                jnp.asarray(failure.q), jnp.asarray(failure.qd), t=jnp.asarray(failure.t), args=args
            )
            output = f": it gave q⁺ = {_fmt(q_r)}, q̇⁺ = {_fmt(qd_r)}"
        except Exception:  # noqa: BLE001 - the message must not hide the failure
            output = ""
    return (
        f"The reset of event {index}{name} (jl.Event(..., reset=...)) returned a non-finite "
        f"state (NaN or inf) {where}, from {state}{output}. A reset maps the state at the "
        "crossing to the state the motion continues from and must be finite there: check "
        "its domain (a square root or log of a negative number, a division by zero)."
    )


def _refused_text(code, failure: Failure, system, args) -> str:
    """The eager messages of the input checks that a compiled program returned as values
    (``jl.NaNOnFailure()``): the initial state is checked again, here on the host, for the
    message with the numbers."""
    compiled = " (Checked inside a compiled program with jl.NaNOnFailure(); the simulation did not start.)"
    if code == FailureCode.SAVE_TIMES:
        index, value = _optional_int(failure.index), _optional_float(failure.value)
        entry = "" if index is None else f": ts[{index}] = {value:g} is not followed by a later time"
        return f"The save times ts must be strictly increasing and finite{entry}." + compiled
    if system is not None:
        q, qd = jnp.asarray(failure.q), jnp.asarray(failure.qd)
        try:
            validate_initial_state(system, q, qd, jnp.asarray(failure.t0, q.dtype), args, None)
        except ValueError as error:
            return str(error) + compiled
    static = FailureCode(code).message.split(" (Raised inside")[0].removeprefix("jaxlag: ")
    return static[0].upper() + static[1:] + compiled


def _result_text(value: int) -> str:
    messages = getattr(diffrax.RESULTS, "_index_to_message", None)
    if messages is not None and 0 <= value < len(messages):
        return messages[value]
    return f"diffrax result {value}"


def _diagnosis(system, failure: Failure, args) -> str:
    try:
        (flags, eig, qdd), (flags1, eig1, q1, qd1) = jax.device_get(
            _probe(system, failure.q, failure.qd, failure.t, failure.dt, args)
        )
    except Exception as error:  # noqa: BLE001 - the diagnosis must not hide the failure
        return f"(Evaluating the equations of motion there raised {type(error).__name__}: {error}.)"
    # The first non-finite quantity in the order of the computation (state, L, M, f, q̈).
    for name in _CAUSES:
        if not flags[name]:
            text = f"There, {_CAUSES[name]} is non-finite."
            if name in ("mass_matrix", "accelerations") and _singular(eig):
                text += f" M is singular there (eigenvalues {_fmt(eig)})."
            elif name == "accelerations" and not getattr(system.mass_solve, "checked", True):
                text += (
                    f" M = ∂²L/∂q̇² has eigenvalues {_fmt(eig)} there: with "
                    "mass_solve=jl.RobustSolve() a state whose (learned) M is not positive definite "
                    "gives NaN, and the run ends at it."
                )
            return text
    if _singular(eig):
        return (
            f"There M = ∂²L/∂q̇² is singular (eigenvalues {_fmt(eig)}): a coordinate "
            "singularity or a degenerate Lagrangian."
        )
    text = f"There everything is finite (|q̈| = {np.max(np.abs(qdd)):.3g}, M eigenvalues {_fmt(eig)})"
    for name in _CAUSES:
        if not flags1[name]:
            if name in _USER_FORCES:
                dt = float(failure.dt)
                t1 = float(failure.t) + (dt if np.isfinite(dt) and dt > 0 else 0.0)
                return (
                    text + f"; one step dt further, at t = {t1:.10g}, q = {_fmt(q1)}, "
                    f"{_CAUSES[name]} is non-finite: that function returns NaN or inf there "
                    "(outside its domain, or a table or law that gives NaN)."
                )
            return (
                text + f"; one step dt further, at q = {_fmt(q1)}, {_CAUSES[name]} is "
                "non-finite: the motion leaves the region where the equations are defined "
                "(e.g. a fractional power or log of a negative number, a square root of a "
                "negative argument, a division by zero)."
            )
    if _singular(eig1):
        return text + f"; one step dt further M is singular (eigenvalues {_fmt(eig1)})."
    return text + "."


# ----------------------------------------------------------------------------- raising
def message(failure: Failure, system=None, args=None, *, args_batched=False, events=None) -> str | None:
    """The full message for a (possibly batched) host failure record, or None.

    ``args`` of a batched record are used for the diagnosis only when ``args_batched`` says
    that they carry the same batch axes."""
    flags = np.asarray(failure.code) != FailureCode.COMPLETED
    members = failed_members(flags)
    if not members:
        return None
    index = members[0]
    if index and not args_batched:
        system = None  # which args belong to the member is unknown: no diagnosis
    member_args = member(args, index) if (index and args is not None) else args
    text = describe(member(failure, index), system, member_args, events)
    if index:
        text = (
            batch_prefix(index, flags, members) + text + " Pass throw=False to keep the "
            "other members' results (traj.failure.code says which failed)."
        )
    return text


def raise_if_failed(failure: Failure, system=None, args=None, *, args_batched=False, events=None) -> None:
    """Raise `SimulationError` eagerly if the (concrete) record says the
    run failed: the host counterpart of `jaxlag._errors.error_if_failed`. ``events``: the run's
    [`Events`][jaxlag.Events] (to name a failed reset)."""
    host = jax.device_get(failure)  # one transfer; blocks until the simulation is done
    text = message(host, system, args, args_batched=args_batched, events=events)
    if text is not None:
        raise SimulationError(text)
