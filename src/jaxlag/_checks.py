"""Run-time checks of the initial state: loud, specific errors instead of silent NaNs.

When the inputs are concrete (``simulate`` called outside ``jit``/``vmap``) the checks run
eagerly and raise ``ValueError`` with the numbers and the offending constraints. Under a
transformation they are compiled into the program as ``Checks.compiled`` says
(`jaxlag._errors.compiled_check`): ``eqx.branched_error_if`` by default, so bad input still
stops the computation, or (``jl.NaNOnFailure()``) values: `initial_refusal` for ``simulate``,
NaN for the other callers.

The compiled checks compute no eigen-decomposition and no SVD: definiteness of ``M`` (its
condition number within a factor n, ``max_i M_ii · trace(M⁻¹)`` from the factor) and
independence of the constraint rows are read from Cholesky factors
(`jaxlag._mechanics.mass_solve.pivots_pass`, `independent_rows`),
written out or looped in ``jax.numpy``. Batched LAPACK eigen-solvers under
``jit(vmap(grad(...)))`` deadlocked jaxlib 0.10's CPU thread pool, and cost more than the
solve they guard. The eager (host) diagnosis still reports the eigenvalues of ``M`` and the
singular values of ``[J; A]``, computed by NumPy.
"""

import abc
import functools as ft

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import DTypeLike
from jaxtyping import Array, Float, PyTree

from . import _compile as compilation
from ._batch_members import batch_prefix, failed_members, member
from ._custom_types import Args, Validated
from ._errors import AbstractOnFailure, FailureCode, RaiseOnFailure, compiled_check
from ._mechanics import constraints as _constraints
from ._mechanics.kkt import accelerations_and_multipliers
from ._mechanics.lagrangian import mass_matrix
from ._mechanics.mass_solve import independent_rows, pivots_pass
from ._misc import is_concrete
from ._tolerances import (
    CONSTRAINT_RCOND,
    MASS_RCOND,
    default_constraint_tolerance,
    rcond,
)


class Checks(eqx.Module):
    """The input checks of [`simulate`][jaxlag.simulate] (``checks=jl.Checks(...)``).

    - ``initial_state``: check ``(q0, qd0)`` before integrating and raise ``ValueError`` if the
      state is non-finite, the mass matrix ``M = ∂²L/∂q̇²`` is singular or not positive
      definite, the constraints are redundant or not finite, a unilateral constraint is
      violated or would have to pull, a floating-point parameter in ``args`` is not finite, or
      the state is off the constraint manifold (``|f|``, ``|ḟ|``, ``|g|``) by more than
      ``constraint_tolerance``. Concrete inputs are checked eagerly on the host (the message
      names the numbers and the constraints); traced ones compile the check into the program.
      See [`consistent_initial_state`][jaxlag.consistent_initial_state] to project an approximate state.
    - ``times``: traced save times ``ts`` (inside ``jit``/``vmap``) are checked to increase
      inside the compiled program. Pass ``False`` when you have checked them yourself (as
      ``jl.fit`` does once on the host): the program then has no host callback for them, so
      JAX's persistent cache can store it. Concrete ``ts`` are always checked, on the host.
    - ``constraint_tolerance``: the largest constraint residual accepted by the initial-state
      check; ``None`` (default) is the dtype's default, 1e-8 in float64 and ``√ε`` (3.5e-4) in
      float32.

    - ``compiled``: what a check does that fails inside a compiled program (inputs traced by
      ``jax.jit``, ``jax.vmap``, ``jax.export``): the checks above and, with ``throw=True``,
      the run's own failure record (non-finite equations, ``max_steps``, ...).
      [`RaiseOnFailure`][jaxlag.RaiseOnFailure] (default) raises a static message through a
      host callback (``eqx.branched_error_if``);
      [`NaNOnFailure`][jaxlag.NaNOnFailure] makes the floating-point outputs of that run NaN
      (their derivatives too) and ``traj.failure.code`` say why
      ([`FailureCode`][jaxlag.FailureCode]: ``INITIAL_STATE``, ``SAVE_TIMES``, ``PARAMETER``
      for the input checks), with no host callback in the program: JAX's persistent cache can
      keep your jitted function and ``jax.export`` can serialize it. Eager calls (concrete
      inputs, also under ``jax.grad`` alone) are checked on the host and raise with the numbers
      either way.

    ``jl.Checks(initial_state=False)`` skips the initial-state check (e.g. when the state comes
    from [`consistent_initial_state`][jaxlag.consistent_initial_state] in the same program).
    """

    initial_state: bool = eqx.field(static=True, default=True)
    times: bool = eqx.field(static=True, default=True)
    constraint_tolerance: float | None = None
    compiled: Validated[AbstractOnFailure] = eqx.field(static=True, default=RaiseOnFailure())

    def __check_init__(self):
        if not isinstance(self.compiled, AbstractOnFailure):
            raise TypeError(
                f"Checks.compiled must be jl.RaiseOnFailure() or jl.NaNOnFailure(); got {self.compiled!r}."
            )
        tolerance = self.constraint_tolerance
        if tolerance is not None and is_concrete(tolerance) and not float(tolerance) > 0:
            raise ValueError(f"Checks.constraint_tolerance must be positive or None; got {tolerance!r}.")

    def tolerance(self, dtype: DTypeLike) -> float:
        """``constraint_tolerance``, or the default of ``dtype`` when it is ``None``."""
        if self.constraint_tolerance is None:
            return default_constraint_tolerance(dtype)
        return self.constraint_tolerance


# ----------------------------------------------------------------------------- the Lagrangian's own checks
class AbstractLagrangianChecks(abc.ABC):
    """Checks that a Lagrangian carries for its own parameters, run with the initial-state check.

    The hook by which a Lagrangian built by an add-on adds checks that only it can make, without
    the core importing the add-on:
    [`jaxlag.coordinates.lagrangian_from_positions`][jaxlag.coordinates.lagrangian_from_positions] returns a
    Lagrangian that implements this interface and checks its bodies (masses, inertias, the pose
    ``R(q0)``, gimbal lock). ``System.lagrangian.fn`` is asked (`lagrangian_checks`); a
    plain function has no checks of its own and gets `NoLagrangianChecks`. The three
    methods are the three ways a check runs: eagerly or compiled in a program
    (`check_initial_state`), or as values that a batch program returns to the host
    (`initial_state_diagnostics`, then `raise_for_diagnostics`).
    """

    @abc.abstractmethod
    def check_initial_state(
        self, system, q: Float[Array, " n"], qd: Float[Array, " n"], t, args: Args
    ) -> Float[Array, " n"]:
        """Check at the initial state: concrete values raise ``ValueError`` with the numbers;
        traced ones return ``q`` carrying ``eqx.branched_error_if`` (static messages)."""

    @abc.abstractmethod
    def initial_state_diagnostics(
        self, system, q: Float[Array, " n"], qd: Float[Array, " n"], t, args: Args
    ) -> PyTree | None:
        """The checks of `check_initial_state` as values, traceable and without a callback,
        or ``None`` when there is nothing to check."""

    @abc.abstractmethod
    def raise_for_diagnostics(self, system, diagnostics: PyTree | None, q) -> None:
        """Raise ``ValueError`` with the numbers for the first batch member whose
        `initial_state_diagnostics` fail (``diagnostics`` and ``q`` with or without a
        leading batch axis)."""


class NoLagrangianChecks(AbstractLagrangianChecks):
    """A Lagrangian with no checks of its own (a plain function): every method does nothing."""

    def check_initial_state(self, system, q, qd, t, args):
        return q

    def initial_state_diagnostics(self, system, q, qd, t, args):
        return None

    def raise_for_diagnostics(self, system, diagnostics, q):
        return None


def lagrangian_checks(system) -> AbstractLagrangianChecks:
    """The checks that ``system``'s Lagrangian carries, or `NoLagrangianChecks`."""
    fn = system.lagrangian.fn
    return fn if isinstance(fn, AbstractLagrangianChecks) else NoLagrangianChecks()


def initial_activity(system, q, qd, t, args, tolerance):
    """Holonomic activity mask at the start: a unilateral constraint acts only where it touches
    (``|f_i| ≤ tolerance``) and does not separate (``ḟ_i ≤ tolerance``). One that touches and
    separates at ``t0`` (a ball thrown up from the floor, ``f = 0``, ``ḟ > 0``) is inactive: the
    body flies, and the segment loop finds its landing (it is "departing" there)."""
    if system.holonomic is None:
        return jnp.zeros((0,), bool)
    f, f_dot, _ = _constraints.constraint_residuals(system, q, qd, t, args)
    active = jnp.ones(f.shape, bool)
    for i in system.unilateral:
        active = active.at[i].set((jnp.abs(f[i]) <= tolerance) & ~(f_dot[i] > tolerance))
    return active


def _traced_diagnostics(system, q, qd, t, args, tolerance, spectra=True):
    """``(values, failures)`` at the initial state, traced into the caller's program.
    ``spectra=False``: without the definiteness and rank tests, and without the failures that
    need them (``None``): for `_diagnostics_on_host`, which computes the eigenvalues and
    singular values with NumPy instead."""
    values = _diagnostic_values(system, q, qd, t, args, tolerance, spectra)
    if not spectra:
        return values, None
    return values, _failures(values, system.least_squares, tolerance, check_mass=system.mass_solve.checked)


#: `_traced_diagnostics` in one compiled call (one host transfer) when called eagerly.
_diagnostics = compilation.filter_jit(_traced_diagnostics)


def _diagnostics_on_host(system, q, qd, t, args, tolerance):
    """``(values, failures)`` of `_diagnostics` as host (NumPy) values, the spectra
    computed by NumPy: the program then has no LAPACK call, whose first lowering in a process
    costs ~0.1 s (JAX registers its kernels), more than the whole check. ``None`` if the
    values are traced (a user function closing over a traced value)."""
    values, _ = _diagnostics(system, q, qd, t, args, tolerance, False)
    if not is_concrete(values):
        return None
    values = with_host_spectra(jax.device_get(values))
    return values, _failures(values, system.least_squares, tolerance, np, system.mass_solve.checked)


def with_host_spectra(values: dict) -> dict:
    """``values`` (host, one state) with the eigenvalues of ``M`` and the singular values of the
    constraint rows, computed by NumPy, for the messages."""
    values = dict(values)
    rows, mass = np.asarray(values["rows"]), np.asarray(values["mass"])
    # LAPACK does not converge on NaN: a non-finite M or J is reported as such (checked first),
    # its spectrum is NaN.
    values["eigenvalues"] = (
        np.linalg.eigvalsh(mass) if np.all(np.isfinite(mass)) else np.full(mass.shape[:1], np.nan, mass.dtype)
    )
    if rows.shape[0] == 0:
        values["singular_values"] = np.ones((1,), rows.dtype)
    elif np.all(np.isfinite(rows)):
        values["singular_values"] = np.linalg.svd(rows, compute_uv=False)
    else:
        values["singular_values"] = np.full((min(rows.shape),), np.nan, rows.dtype)
    return values


def _diagnostic_values(system, q, qd, t, args, tolerance, spectra=True):
    system.check(q, qd, t, args)
    mass = mass_matrix(system, q, qd, t, args)
    f, f_dot, g = _constraints.constraint_residuals(system, q, qd, t, args)
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    active = initial_activity(system, q, qd, t, args, tolerance)
    unilateral = jnp.zeros(f.shape, bool)
    for i in system.unilateral:
        unilateral = unilateral.at[i].set(True)
    row_weight = jnp.concatenate([active, jnp.ones(g.shape, bool)]).astype(q.dtype)
    if system.unilateral:
        _, lam, _ = accelerations_and_multipliers(system, q, qd, t, args, active=active)
        scale = 1.0 + jnp.max(jnp.abs(lam))
        wrong_sign = jnp.any(active & unilateral & (lam < -tolerance * scale))
    else:
        wrong_sign = jnp.asarray(False)
    off_diagonal = mass - jnp.diag(jnp.diagonal(mass))
    not_diagonal = system.diagonal_mass & ~(
        jnp.max(jnp.abs(off_diagonal)) <= rcond(1e-12, q.dtype) * jnp.max(jnp.abs(mass))
    )
    parameters = [jnp.all(jnp.isfinite(x)) for x in _inexact_leaves(args)]
    if spectra:
        # Cholesky pivots, not eigenvalues or singular values (see the module docstring).
        spectra = dict(
            mass_ok=pivots_pass(mass, rcond(MASS_RCOND, q.dtype)),
            rows_independent=independent_rows(rows * row_weight[:, None], rcond(CONSTRAINT_RCOND, q.dtype)),
        )
    else:
        spectra = {}
    return dict(
        **spectra,
        finite=jnp.all(jnp.isfinite(q)) & jnp.all(jnp.isfinite(qd)),
        args_finite=jnp.stack(parameters) if parameters else jnp.ones((0,), bool),
        constraints_finite=jnp.all(jnp.isfinite(f)) & jnp.all(jnp.isfinite(f_dot)) & jnp.all(jnp.isfinite(g)),
        residuals_finite=jnp.all(jnp.isfinite(f)) & jnp.all(jnp.isfinite(g)),
        mass_finite=jnp.all(jnp.isfinite(mass)),
        jacobian_finite=jnp.all(jnp.isfinite(rows)),
        not_diagonal=not_diagonal,
        mass=mass,
        f=jnp.where(active, f, 0.0),
        f_dot=jnp.where(active, f_dot, 0.0),
        f_raw=f,
        g=g,
        rows=rows * row_weight[:, None],
        num_active=jnp.sum(row_weight),
        violated=jnp.any(unilateral & (f < -tolerance)),
        wrong_sign=wrong_sign,
    )


def _is_inexact(x) -> bool:
    return isinstance(x, (jax.Array, np.ndarray, np.generic, float, complex)) and jnp.issubdtype(
        jnp.result_type(x), jnp.inexact
    )


def _inexact_leaves(tree):
    return [x for x in jax.tree.leaves(tree) if _is_inexact(x)]


def _inexact_names(tree) -> list[str]:
    return [
        f"args{jax.tree_util.keystr(path)}"
        for path, x in jax.tree_util.tree_leaves_with_path(tree)
        if _is_inexact(x)
    ]


def unmarked_batch_hint(args, args_axes) -> str:
    """For ``simulate_batch``'s "nothing to batch": the ``args`` leaves with a leading axis that
    ``args_axes`` leaves shared (a forgotten ``args_axes``), or ``""``."""
    if args_axes is not None:
        return ""
    arrays = [
        (path, jnp.shape(x)) for path, x in jax.tree_util.tree_leaves_with_path(args) if jnp.ndim(x) >= 1
    ]
    if not arrays:
        return ""
    names = ", ".join(f"args{jax.tree_util.keystr(path)} (shape {shape})" for path, shape in arrays[:4])
    return (
        f" args_axes is None, so every args leaf is shared, including {names}: if these hold "
        "one value per member, pass args_axes=0 (all leaves) or a dict like args with 0 at the "
        "batched leaves and None at the shared ones."
    )


def _failures(d, least_squares: bool, tolerance: float, xp=jnp, check_mass: bool = True):
    """Which checks fail, from `_diagnostic_values` (``xp``: ``jax.numpy`` in a program,
    ``numpy`` on the host). In a program the definiteness and rank tests are Cholesky pivots
    (``mass_ok``, ``rows_independent``); on the host the eigenvalues and singular values (the
    same thresholds, ``MASS_RCOND`` and ``CONSTRAINT_RCOND``). ``check_mass=False``
    ([`RobustSolve`][jaxlag.RobustSolve]): a mass matrix that is not positive definite is no error."""
    dtype = d["mass"].dtype
    if "eigenvalues" in d:
        eig = d["eigenvalues"]
        mass_bad = ~(eig[0] > rcond(MASS_RCOND, eig.dtype) * xp.max(xp.abs(eig)))
        sv = d["singular_values"]
        # As a float: num_active is a sum of 0/1 row weights (no implicit int/float promotion).
        rank = xp.sum(sv > rcond(CONSTRAINT_RCOND, sv.dtype) * sv[0]).astype(d["num_active"].dtype)
        dependent = rank < d["num_active"]
    else:
        mass_bad, dependent = ~d["mass_ok"], ~d["rows_independent"]
    residual = xp.concatenate([xp.abs(d["f"]), xp.abs(d["f_dot"]), xp.abs(d["g"]), xp.zeros((1,), dtype)])
    no = xp.asarray(False)
    return dict(
        nonfinite=~d["finite"],
        nonfinite_args=~xp.all(d["args_finite"]),
        nonfinite_mass=~d["mass_finite"] if check_mass else no,
        # f and g finite, their derivative not (sqrt(x²) at 0): before the residual check, which
        # ḟ = J q̇ then fails as a consequence.
        nonfinite_jacobian=d["residuals_finite"] & ~d["jacobian_finite"],
        nonfinite_constraints=~d["constraints_finite"],
        not_diagonal=d["not_diagonal"],
        mass=mass_bad if check_mass else no,
        rank=no if least_squares or d["rows"].shape[0] == 0 else dependent,
        off_manifold=~(xp.max(residual) <= tolerance),
        violated=d["violated"],
        wrong_sign=d["wrong_sign"],
    )


def _dependent_rows(rows: np.ndarray, m_h: int) -> list[str]:
    """Name each constraint row that is a linear combination of the rows before it."""
    found, kept = [], []
    for i in range(rows.shape[0]):
        candidate = np.array(kept + [rows[i]])
        sv = np.linalg.svd(candidate, compute_uv=False)
        rank = int(np.sum(sv > rcond(CONSTRAINT_RCOND, rows.dtype) * max(sv[0], 1e-300)))
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


def _tolerance_text(tolerance: float, dtype) -> str:
    text = f"{tolerance:g}"
    if np.dtype(dtype) != np.float64:
        text += (
            f" (the state is {np.dtype(dtype).name}: jax_enable_x64 is off; enable it with "
            "jax.config.update('jax_enable_x64', True), or pass "
            "checks=jl.Checks(constraint_tolerance=...) suited to single precision)"
        )
    return text


class _Static(eqx.Module):
    """What the message needs besides the numbers (hashable: closed over by the callback)."""

    unilateral: tuple = eqx.field(static=True)
    tolerance: float = eqx.field(static=True)
    arg_names: tuple = eqx.field(static=True)


#: Arrays up to this size are printed whole in messages; longer ones are summarized.
_WHOLE = 8


def _values(label: str, x, index: str | None = None, tolerance: float = 0.0, worst: int = 3) -> str:
    """``label = [...]`` for a short array; for a long one (a 100-link chain) its size, norm and
    the largest entries with their indices (``index[i] = value``), with how many exceed
    ``tolerance``."""
    x = np.asarray(x)
    if x.size <= _WHOLE:
        return f"{label} = {x}"
    index = index or label
    flat = x.ravel()
    magnitude = np.where(np.isfinite(flat), np.abs(flat), np.inf)
    beyond = int(np.sum(magnitude > tolerance))
    if beyond == 0:
        return (
            f"{label} = 0 in all {x.size} entries"
            if tolerance == 0
            else f"{label}: all {x.size} within tolerance"
        )
    largest = np.argsort(-magnitude, kind="stable")[: min(worst, beyond)]
    entries = ", ".join(f"{index}[{int(i)}] = {flat[i]:.3g}" for i in largest)
    count = f"{beyond} of {x.size} entries beyond {tolerance:g}" if tolerance > 0 else f"{x.size} entries"
    return f"{label}: {count}, norm {np.linalg.norm(flat):.3g}, largest {entries}"


def _nonfinite_entries(label: str, x, worst: int = 4) -> str:
    """``label[i] = nan, ...`` for the non-finite entries of ``x`` (all of a short array)."""
    x = np.asarray(x)
    if x.size <= _WHOLE:
        return f"{label} = {x}"
    bad = np.flatnonzero(~np.isfinite(x))
    shown = ", ".join(f"{label}[{int(i)}] = {x.ravel()[i]}" for i in bad[:worst])
    more = f" and {bad.size - worst} more" if bad.size > worst else ""
    return f"{shown}{more} (of {x.size})" if bad.size else f"{label} finite"


def _spectrum(x) -> str:
    x = np.asarray(x)
    if x.size <= _WHOLE:
        return str(x)
    return f"{x.size} values from {np.min(x):.3g} to {np.max(x):.3g}"


def _nonfinite_rows(rows, m_h: int, limit: int = 4) -> str:
    """``∂f_i/∂q_j = nan at J[i, j] (holonomic[i], q[j])`` for the non-finite entries of the
    constraint rows ``[J; A]``."""
    bad = np.argwhere(~np.isfinite(np.asarray(rows)))
    named = []
    for i, j in bad[:limit]:
        value = np.asarray(rows)[i, j]
        if i < m_h:
            named.append(f"J[{i}, {j}] = ∂f_{i}/∂q_{j} = {value} (holonomic[{i}], q[{j}])")
        else:
            named.append(f"A[{i - m_h}, {j}] = ∂g_{i - m_h}/∂q̇_{j} = {value} (velocity[{i - m_h}], q̇[{j}])")
    more = f", and {len(bad) - limit} more" if len(bad) > limit else ""
    return "; ".join(named) + more


def _initial_message(d, fail, static: _Static, where: str = "at the initial state") -> str | None:
    """The message for one member's host diagnostics, or None (shared by both paths)."""
    if not any(bool(x) for x in fail.values()):
        return None
    if bool(fail.get("nonfinite", False)):
        return (
            f"The initial state is not finite: {_nonfinite_entries('q0', d['q'])}, "
            f"{_nonfinite_entries('qd0', d['qd'])}."
        )
    if bool(fail.get("nonfinite_args", False)):
        bad = [name for name, ok in zip(static.arg_names, np.asarray(d["args_finite"])) if not ok]
        return (
            f"A parameter in args is not finite (NaN or inf): {', '.join(bad)}. Every "
            "floating-point leaf of args must be finite."
        )
    if bool(fail.get("nonfinite_mass", False)):
        mass = np.asarray(d["mass"]) if "mass" in d else None
        entries = ""
        if mass is not None:
            bad = np.argwhere(~np.isfinite(mass))[:4]
            entries = ": " + ", ".join(f"M[{i}, {j}] = {mass[i, j]}" for i, j in bad)
        return (
            f"The mass matrix M = ∂²L/∂q̇² is not finite {where}{entries}. L is finite but its "
            "second derivative in q̇ is not: a kinetic term that is not twice differentiable "
            "there (|q̇| written as sqrt(q̇²), a norm of a zero vector, a fractional power of "
            "zero). Write the kinetic energy with squares (½ m q̇², ½ m |v|² as v @ v)."
        )
    if bool(fail.get("mass", False)):
        return (
            f"The mass matrix M = ∂²L/∂q̇² is singular or not positive definite {where} "
            f"(eigenvalues {_spectrum(d['eigenvalues'])}). The Lagrangian is degenerate: "
            "every coordinate needs a kinetic term with a positive coefficient" + _SINGULAR_COORDINATES
        )
    if bool(fail.get("nonfinite_jacobian", False)):
        m_h = np.asarray(d["f"]).shape[0]
        return (
            f"The constraint Jacobian is not finite {where}, although the constraints are: "
            f"{_nonfinite_rows(d['rows'], m_h)} ({_values('f(q0)', d['f_raw'], 'f')}, "
            f"{_values('q0', d['q'])}). The constraint function is not differentiable there: "
            "|x| written as sqrt(x**2) or a norm of a zero vector at x = 0, a square root or "
            "fractional power of zero, arctan2(0, 0). Write it in a differentiable form "
            "(e.g. x**2 - r**2 instead of |x| - r, jnp.abs instead of sqrt(x**2)), or start "
            "away from that point."
        )
    if bool(fail.get("nonfinite_constraints", False)):
        return (
            f"The constraint functions are not finite {where}: {_values('f(q0)', d['f_raw'], 'f')}, "
            f"{_values('ḟ', d['f_dot'])}, {_values('g', d['g'])} ({_values('q0', d['q'])})."
        )
    if bool(fail.get("not_diagonal", False)):
        matrix = f":\n{np.asarray(d['mass'])}" if "mass" in d else " (call outside jit to see M)."
        return (
            "The system declares diagonal_mass=True, but M = ∂²L/∂q̇² has off-diagonal "
            f"entries {where}" + matrix
        )
    if bool(fail.get("rank", False)):
        m_h = d["f"].shape[0]
        names = (
            _dependent_rows(np.asarray(d["rows"]), m_h)
            if "rows" in d
            else ["(call simulate outside jit to see which)"]
        )
        return (
            f"The constraints are redundant or conflicting {where}: the constraint "
            f"Jacobian [J; A] (singular values {_spectrum(d['singular_values'])}) is rank "
            f"deficient; dependent rows: {', '.join(names)}. Remove them, or pass "
            "least_squares=True to jl.System to accept consistent redundant constraints "
            "(minimum-norm multipliers)."
        )
    if bool(fail.get("violated", False)):
        f_raw = np.asarray(d["f_raw"])
        violated = [i for i in static.unilateral if f_raw[i] < -static.tolerance]
        shown = ", ".join(f"f[{i}] = {f_raw[i]:.6g}" for i in violated[:6])
        return (
            f"A unilateral constraint is violated at the initial state (f_i < 0): {shown} "
            f"(unilateral indices {static.unilateral}). One-sided constraints are written "
            "f_i(q, t) >= 0."
        )
    if bool(fail.get("off_manifold", False)):
        return (
            "The initial state is off the constraint manifold beyond the tolerance "
            f"{_tolerance_text(static.tolerance, np.asarray(d['q']).dtype)}: "
            + ", ".join(
                _values(label, d[key], index, static.tolerance)
                for label, key, index in (
                    ("f(q0)", "f", "f"),
                    ("ḟ = J q̇0 + ∂f/∂t", "f_dot", "ḟ"),
                    ("velocity constraints g", "g", "g"),
                )
            )
            + ". "
            + _POINTER
        )
    if bool(fail.get("wrong_sign", False)):
        return (
            "A unilateral constraint in contact at t0 has a multiplier of the wrong sign: it "
            "would have to pull (λ_i < 0) to hold, so it cannot be in contact. Start the motion "
            f"off the constraint (f_i > 0) instead. {_values('f(q0)', d['f_raw'], 'f')}."
        )
    return None


def _batched_initial_message(static: _Static, payload) -> str | None:
    """`_initial_message` for the first failed member of a (possibly batched) payload."""

    d, fail = payload
    flags = ft.reduce(np.logical_or, [np.asarray(x) for x in fail.values()])
    members = failed_members(flags)
    if not members:
        return None
    index = members[0]
    d_member, fail_member = member((d, fail), index)
    text = _initial_message(with_host_spectra(d_member), fail_member, static)
    return batch_prefix(index, flags, members) + (text or "")


def validate_initial_state(system, q, qd, t, args, tolerance: float | Float[Array, ""] | None):
    """Check the initial state; return ``(q, qd)`` (threaded through the run-time checks).

    Concrete inputs raise ``ValueError`` here, with the numbers; traced ones compile the check
    into the program (``eqx.branched_error_if``), which raises the static message of the first
    failing check when the program runs."""

    if tolerance is None:
        tolerance = default_constraint_tolerance(jnp.result_type(q))
    static = _Static(tuple(system.unilateral), float(tolerance), tuple(_inexact_names(args)))
    # The Lagrangian's own checks (rigid bodies: mass, inertia, R(q0), gimbal lock) come first.
    q = lagrangian_checks(system).check_initial_state(system, q, qd, t, args)
    if is_concrete((q, qd, t, args)):
        host = _diagnostics_on_host(system, q, qd, t, args, tolerance)
        if host is not None:
            d, fail = host
            text = _initial_message(dict(d, q=np.asarray(q), qd=np.asarray(qd)), fail, static)
            if text is not None:
                raise ValueError(text)
            return q, qd
    d, fail = _diagnostics(system, q, qd, t, args, tolerance)
    d = dict(d, q=q, qd=qd)
    # Concrete inputs can still give traced flags: a user function may close over a traced value.
    if is_concrete((q, qd, t, args, fail)):
        d_host, fail_host = jax.device_get((d, fail))  # one transfer; fetched only to report
        text = _initial_message(with_host_spectra(d_host), fail_host, static)
        if text is not None:
            raise ValueError(text)
        return q, qd
    # Compiled: the static message names the first failing check; the numbers are what the eager
    # call (outside the transformation) reports.
    q = _error_if_any(q, fail, _INITIAL_CAUSES, _INITIAL_MESSAGES)
    return q, qd


def initial_state_diagnostics(system, q, qd, t, args, tolerance):
    """``(values, failures)`` of the initial-state check as values (traceable, no callback):
    for programs that return their checks to the host (`raise_for_initial_states`).

    Traced into the caller's program, which maps it over the batch: as a jit of its own it would
    be traced for one member first and that trace batched afterwards, a second pass over every
    operation (the compiled program is the same: XLA inlines the call)."""
    d, fail = _traced_diagnostics(system, q, qd, t, args, tolerance)
    own = lagrangian_checks(system).initial_state_diagnostics(system, q, qd, t, args)
    return dict(d, q=q, qd=qd, lagrangian=own), fail


def raise_for_initial_states(system, diagnostics, args, tolerance) -> None:
    """Raise ``ValueError`` on the host for the first failing member of (batched)
    `initial_state_diagnostics`, with the message of `validate_initial_state`."""
    d, fail = jax.device_get(diagnostics)
    # The Lagrangian's own checks first, as in validate_initial_state.
    lagrangian_checks(system).raise_for_diagnostics(system, d.get("lagrangian"), d["q"])
    static = _Static(tuple(system.unilateral), float(tolerance), tuple(_inexact_names(args)))
    text = _batched_initial_message(static, (d, fail))
    if text is not None:
        raise ValueError(text)


# ----------------------------------------------------------------------------- System methods
def _state_message(what: str, static: _Static, payload) -> str | None:
    """Why ``System.<what>`` is not finite at a state (first failing member of a batch)."""

    bad, d, fail = payload
    members = failed_members(np.asarray(bad))
    if not members:
        return None
    index = members[0]
    bad_i, d_i, fail_i = member((bad, d, fail), index)
    text = _initial_message(d_i, fail_i, static, where="at this state")
    if text is None:
        text = (
            "L, M and the constraints are regular here; a force, dissipation or constraint "
            "function returns NaN or inf, or the state is outside their domain."
        )
    state = f"q = {np.asarray(d_i['q'])}, q̇ = {np.asarray(d_i['qd'])}"
    return batch_prefix(index, bad, members) + f"System.{what} is not finite at {state}: {text}"


_STATE_CHECKS = (
    "nonfinite",
    "nonfinite_args",
    "nonfinite_mass",
    "mass",
    "nonfinite_jacobian",
    "nonfinite_constraints",
    "rank",
)

#: Ends the singular-M messages: coordinates can be singular where the Lagrangian is not.
_SINGULAR_COORDINATES = (
    ", or the coordinates are singular there (Euler angles at gimbal lock: 'zxz' at θ = 0 or π, "
    "'zyx' at pitch ±π/2; use a quaternion body, which has none, or start away from it)."
)

_COMPILED = (
    " (Checked inside a compiled program: call outside jit/vmap/grad to see the numbers"
    " and the offending constraints.)"
)

_NONFINITE_MASS = "The mass matrix M = ∂²L/∂q̇² is not finite (NaN or inf)"
_NONFINITE_JACOBIAN = (
    "The constraint Jacobian (J = ∂f/∂q, or A = ∂g/∂q̇) is not finite (NaN or inf): the "
    "constraint function is not differentiable there (|x| as sqrt(x**2) at 0, a norm of a zero "
    "vector)"
)

#: The compiled initial-state checks, in the order of the eager diagnosis, and their static
#: messages (the eager message adds the numbers).
_INITIAL_CAUSES = (
    "nonfinite",
    "nonfinite_args",
    "nonfinite_mass",
    "mass",
    "nonfinite_jacobian",
    "nonfinite_constraints",
    "not_diagonal",
    "rank",
    "violated",
    "off_manifold",
    "wrong_sign",
)
_INITIAL_MESSAGES = tuple(
    "jaxlag: " + text + _COMPILED
    for text in (
        "The initial state is not finite.",
        "A parameter in args is not finite (NaN or inf); every floating-point leaf of args must be finite.",
        _NONFINITE_MASS + " at the initial state.",
        "The mass matrix M = ∂²L/∂q̇² is singular or not positive definite at the initial state. "
        "The Lagrangian is degenerate: every coordinate needs a kinetic term with a positive "
        "coefficient" + _SINGULAR_COORDINATES,
        _NONFINITE_JACOBIAN + " at the initial state, although the constraints are finite.",
        "The constraint functions are not finite at the initial state.",
        "The system declares diagonal_mass=True, but M = ∂²L/∂q̇² has off-diagonal entries.",
        "The constraints are redundant or conflicting at the initial state: the constraint Jacobian "
        "[J; A] is rank deficient. Remove the dependent rows, or pass least_squares=True to "
        "jl.System to accept consistent redundant constraints.",
        "A unilateral constraint is violated at the initial state (f_i < 0).",
        "The initial state is off the constraint manifold beyond the tolerance. " + _POINTER,
        "A unilateral constraint in contact at t0 has a multiplier of the wrong sign: it would "
        "have to pull to hold.",
    )
)

_STATE_MESSAGES = tuple(
    text + _COMPILED
    for text in (
        "the state is not finite.",
        "a parameter in args is not finite.",
        "the mass matrix M = ∂²L/∂q̇² is not finite.",
        "the mass matrix M = ∂²L/∂q̇² is singular or not positive definite" + _SINGULAR_COORDINATES,
        "the constraint Jacobian is not finite, although the constraints are.",
        "the constraint functions are not finite.",
        "the constraints are redundant or conflicting (rank-deficient constraint Jacobian).",
        "the result is not finite: a force, dissipation or constraint function returns NaN or inf, "
        "or the state is outside their domain.",
    )
)


assert len(_INITIAL_MESSAGES) == len(_INITIAL_CAUSES) and len(_STATE_MESSAGES) == len(_STATE_CHECKS) + 1


def _error_if_any(x, fail: dict, causes: tuple[str, ...], messages: tuple[str, ...]):
    """``x``, checked (`jaxlag._errors.compiled_check`: ``eqx.branched_error_if`` by default)
    with the static message of the first failing cause (for a batch under ``RaiseOnFailure``:
    the latest cause in the list that some member fails)."""
    flags = jnp.stack([jnp.any(jnp.asarray(fail[cause])) for cause in causes])
    return compiled_check(x, jnp.any(flags), jnp.argmax(flags), messages)


#: The position of the non-finite-parameter cause among the flags of `initial_refusal` (the
#: Lagrangian's own checks come first).
_ARGS_FLAG = 1 + _INITIAL_CAUSES.index("nonfinite_args")


def initial_refusal(system, q, qd, t, args, tolerance: float | None) -> tuple[Array, Array, Array]:
    """The initial-state check of `validate_initial_state` as values, with no host callback:
    ``(code, index, value)`` for `jaxlag._errors.refused`. ``code`` is
    `FailureCode.PARAMETER` for a non-finite floating-point leaf of ``args`` (``index``: its
    position among them), `FailureCode.INITIAL_STATE` for every other failed check (``index``:
    0 the Lagrangian's own checks, then the causes of the eager diagnosis in order, see
    `FailureCode`), else ``COMPLETED``; ``value`` is NaN. The first failed check in the order
    of the eager diagnosis decides."""
    if tolerance is None:
        tolerance = default_constraint_tolerance(jnp.result_type(q))
    d, fail = _diagnostics(system, q, qd, t, args, tolerance)
    own = lagrangian_checks(system).initial_state_diagnostics(system, q, qd, t, args)
    own_failed = jnp.asarray(False) if own is None else jnp.any(own[1])
    flags = jnp.stack([own_failed] + [jnp.any(jnp.asarray(fail[cause])) for cause in _INITIAL_CAUSES])
    first = jnp.argmax(flags)
    parameter = first == _ARGS_FLAG
    finite_leaves = d["args_finite"]
    leaf = jnp.argmax(~finite_leaves) if finite_leaves.shape[0] else jnp.asarray(0)
    code = jnp.where(
        jnp.any(flags),
        jnp.where(parameter, FailureCode.PARAMETER, FailureCode.INITIAL_STATE),
        FailureCode.COMPLETED,
    )
    index = jnp.where(parameter, leaf, jnp.where(first > _ARGS_FLAG, first - 1, first))
    value = jnp.asarray(jnp.nan, jnp.result_type(q))
    return code.astype(jnp.int32), index.astype(jnp.int32), value


def check_state_result(system, what: str, out, q, qd, t, args):
    """``out`` (a result of a System method at one state), or a ``ValueError`` naming why it
    cannot be trusted: a singular or indefinite mass matrix, redundant constraints, non-finite
    inputs or a non-finite result (a singular M gives huge finite accelerations, not NaN, so
    definiteness is checked, with the thresholds of the initial-state check: eigenvalues on the
    host, Cholesky pivots in a program). Eager for concrete values (the diagnostics program is
    the one ``simulate``'s check compiles); compiled in otherwise, with no eigen-decomposition
    or SVD. Not called for [`RobustSolve`][jaxlag.RobustSolve] systems, whose failed states are NaN."""

    tolerance = default_constraint_tolerance(jnp.result_type(q))
    static = _Static(tuple(system.unilateral), tolerance, tuple(_inexact_names(args)))
    q = lagrangian_checks(system).check_initial_state(system, q, qd, t, args)
    host = None
    if is_concrete((out, q, qd, t, args)):
        host = _diagnostics_on_host(system, q, qd, t, args, tolerance)
    if host is not None:
        d, fail = host
        flags = {k: fail[k] for k in _STATE_CHECKS}
        bad = not np.all(np.isfinite(jax.device_get(out)))
        if bad or any(bool(x) for x in flags.values()):
            raise ValueError(_state_message(what, static, (True, dict(d, q=q, qd=qd), flags)))
        return out
    d = _diagnostic_values(system, q, qd, t, args, tolerance)
    fail = _failures(d, system.least_squares, tolerance)
    flags = {k: fail[k] for k in _STATE_CHECKS}
    flags = {**flags, "nonfinite_result": ~jnp.all(jnp.isfinite(out))}
    messages = tuple(
        f"jaxlag: System.{what} cannot be trusted at this state: {text}" for text in _STATE_MESSAGES
    )
    return _error_if_any(out, flags, (*_STATE_CHECKS, "nonfinite_result"), messages)
