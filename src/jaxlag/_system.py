"""``System``: a Lagrangian with its constraints and non-conservative forces, as a pytree."""

from collections.abc import Callable, Sequence

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float

from . import _compile as compilation
from ._checks import check_state_result, initial_activity
from ._conventions import (
    UserFunction,
    as_array_leaves,
    wrap_configuration_function,
    wrap_state_function,
)
from ._conventions import _wrap as _wrap_function
from ._custom_types import Args, Coordinates, Matrix, RealScalarLike, Scalar, Validated, Vector, Velocities
from ._mechanics import constraints as _constraints
from ._mechanics import kkt as _kkt
from ._mechanics import lagrangian as _mechanics
from ._mechanics.constant_mass import ConstantMass
from ._mechanics.dynamics import AbstractDynamics, AutodiffDynamics
from ._mechanics.friction import Coulomb, as_friction
from ._mechanics.impacts import Unilateral, as_unilateral
from ._mechanics.mass_solve import AbstractMassSolve, CheckedCholesky
from ._tolerances import default_constraint_tolerance


class System(eqx.Module):
    r"""A mechanical system: ``L(q, q̇, t)`` plus constraints and non-conservative forces.

    Every function follows one convention (see [the calling convention][the-calling-convention]):
    state positionally, ``t`` and ``args`` by keyword if declared.

    **Arguments:**

    - ``lagrangian``: ``L(q, qd, [t], [args]) -> scalar``.
    - ``holonomic``: ``f(q, [t], [args]) -> (m_h,)``; the motion keeps ``f = 0``.
    - ``velocity_constraints``: ``g(q, qd, [t], [args]) -> (m_v,)``, affine in ``qd``
      (Pfaffian ``A(q, t) q̇ + b(q, t) = 0``, e.g. rolling without slipping).
    - ``dissipation``: Rayleigh function ``R(q, qd, [t], [args]) -> scalar``; force ``−∂R/∂q̇``.
    - ``forces``: external generalized forces ``Q(q, qd, [t], [args]) -> (n,)``.
    - ``actuation``: the generalized forces of a control input ``u``,
      ``Q_u(q, qd, u, [t], [args]) -> (n,)``, e.g. a horizontal force on a cart
      ``lambda q, qd, u: jnp.stack([u, 0.0])``. ``u`` enters as a generalized force:
      ``M q̈ = F + Q_u(q, q̇, u, t) + Jᵀλ + Aᵀμ``. [`jaxlag.analysis.linearize`][jaxlag.analysis.linearize]
      turns it into
      the input matrix ``B = ∂(q̇, q̈)/∂u``.
    - ``control``: the law giving the input, ``u = control(q, qd, [t], [args])``, a scalar or a
      1-D array (k,): a feedback law, a time table (``lambda q, qd, t, args: args["u"](t)``
      with a `jaxlag.inputs` table in ``args``), or both. Gains and tables in ``args`` make
      one ``System`` serve open loop, linearization and closed loop; `with_control`
      returns a copy with another law. A system with ``actuation`` needs a control law to be
      simulated (there is no implied ``u = 0``: the size of ``u`` is the law's), and
      [`linearize`][jaxlag.analysis.linearize] accepts ``u=`` instead.
    - ``least_squares``: accept redundant constraints (singular ``J M⁻¹ Jᵀ``) and report the
      minimum-norm multipliers instead of raising.
    - ``diagonal_mass``: declare ``M`` diagonal (Cartesian particles): ``M⁻¹`` is then a division,
      not a Cholesky factorization. Checked at the initial state.
    - ``mass_solve``: how ``M q̈ = F + Jᵀλ + Aᵀμ`` is solved, a
      [`AbstractMassSolve`][jaxlag.AbstractMassSolve]. ``jl.CheckedCholesky()`` (default): a state whose
      ``M`` is not positive definite is an error (raised with the numbers). ``jl.RobustSolve()``,
      for learned Lagrangians: such a state gives NaN accelerations and multipliers for that
      state alone (under ``vmap``, one member), never an error, with a zero gradient; count them
      with ``jnp.isnan(qdd).any(-1).sum()``.
    - ``dynamics``: where ``M`` and the Lagrangian forces
      ``F_L = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t`` of the equations of motion come from, an
      [`AbstractDynamics`][jaxlag.AbstractDynamics]. ``jl.AutodiffDynamics()`` (default):
      automatic differentiation of ``L``. Another implementation computes the same ``M`` and
      ``F_L`` of the same ``L`` faster (a kinematic tree's recursive algorithms,
      [`jaxlag.robots.TreeDynamics`][jaxlag.robots.TreeDynamics]); the dissipation, ``forces``
      and ``actuation`` are added to its ``F_L`` as to the default's, and momenta, energy and
      the variational integrator still come from ``L``.
    - ``unilateral``: indices of holonomic constraints that are one-sided, ``f_i(q, t) ≥ 0``
      with ``λ_i ≥ 0`` while in contact (a particle on the outside of a sphere ``r − R ≥ 0``,
      a string ``l − r ≥ 0``). [`simulate`][jaxlag.simulate] releases such a constraint when its
      multiplier crosses zero and re-engages it (perfectly plastic impact) when ``f_i`` returns
      to zero. ``unilateral=jl.Unilateral(indices, restitution=e)`` sets Newton's coefficient
      of restitution ``ḟ⁺ = −e ḟ⁻`` at the impacts (the body rebounds for ``e > 0``).
    - ``friction``: [`Coulomb`][jaxlag.Coulomb] elements (one or a sequence), Coulomb friction on
      contact rows as a stick–slip element: ``M q̈ = F + Jᵀλ + Aᵀμ + Tᵀλ_t`` with
      ``λ_t = −μ sign(v_t) λ_N`` while slipping and ``v_t = 0`` while ``|λ_t| ≤ μ λ_N``.

    Equations of motion (sign convention of the seeds):
    ``d/dt ∂L/∂q̇ − ∂L/∂q = Jᵀλ + Aᵀμ − ∂R/∂q̇ + Q``, i.e. ``M q̈ = F + Jᵀλ + Aᵀμ``.
    """

    lagrangian: UserFunction
    holonomic: UserFunction | None
    velocity_constraints: UserFunction | None
    dissipation: UserFunction | None
    forces: UserFunction | None
    actuation: UserFunction | None
    control: UserFunction | None
    least_squares: bool = eqx.field(static=True)
    unilateral: tuple[int, ...] = eqx.field(static=True)
    diagonal_mass: bool = eqx.field(static=True)
    mass_solve: AbstractMassSolve = CheckedCholesky()
    dynamics: AbstractDynamics = AutodiffDynamics()
    # Set by simulate while tracing when M does not depend on the state (jaxlag._mechanics.constant_mass).
    constant_mass: ConstantMass | None = None
    # The impact law of the unilateral constraints (restitution); None: plastic (jaxlag._mechanics.impacts).
    unilateral_law: Unilateral | None = None
    # Coulomb friction elements on contact rows (jaxlag._mechanics.friction); () without friction.
    friction: tuple[Coulomb, ...] = ()

    def __init__(
        self,
        lagrangian: Validated[Callable],
        holonomic: Validated[Callable | None] = None,
        *,
        velocity_constraints: Validated[Callable | None] = None,
        dissipation: Validated[Callable | None] = None,
        forces: Validated[Callable | None] = None,
        actuation: Validated[Callable | None] = None,
        control: Validated[Callable | None] = None,
        least_squares: bool = False,
        unilateral: Validated[int | Sequence[int] | Unilateral] = (),
        diagonal_mass: bool = False,
        mass_solve: Validated[AbstractMassSolve] = CheckedCholesky(),
        friction: Validated[Coulomb | Sequence[Coulomb] | None] = None,
        dynamics: Validated[AbstractDynamics] = AutodiffDynamics(),
    ):
        self.lagrangian = wrap_state_function(lagrangian, "lagrangian")
        self.holonomic = wrap_configuration_function(holonomic, "holonomic constraint function")
        self.velocity_constraints = wrap_state_function(velocity_constraints, "velocity constraint function")
        self.dissipation = wrap_state_function(dissipation, "dissipation function")
        self.forces = wrap_state_function(forces, "force function")
        self.actuation = _wrap_actuation(actuation)
        self.control = wrap_state_function(control, "control law")
        if control is not None and actuation is None:
            raise ValueError(_CONTROL_WITHOUT_ACTUATION)
        self.least_squares = bool(least_squares)
        self.diagonal_mass = bool(diagonal_mass)
        if not isinstance(mass_solve, AbstractMassSolve):
            raise TypeError(
                "mass_solve must be jl.CheckedCholesky() or jl.RobustSolve(); got "
                f"{type(mass_solve).__name__}."
            )
        self.mass_solve = mass_solve
        if not isinstance(dynamics, AbstractDynamics):
            raise TypeError(
                "dynamics must be a jl.AbstractDynamics (jl.AutodiffDynamics(), or e.g. "
                f"jaxlag.robots.TreeDynamics(tree)); got {type(dynamics).__name__}."
            )
        self.dynamics = dynamics
        self.constant_mass = None
        law = as_unilateral(unilateral)
        self.unilateral = law.indices
        self.unilateral_law = law if isinstance(unilateral, Unilateral) else None
        if self.unilateral and holonomic is None:
            raise ValueError("unilateral names holonomic constraints, but no holonomic function was given.")
        self.friction = as_friction(friction)
        if self.friction and holonomic is None:
            raise ValueError("friction acts on contact rows of the holonomic constraints; none was given.")
        if self.friction:
            if self.least_squares:
                raise ValueError(
                    "friction with least_squares=True is not supported: the frictional KKT "
                    "matrix is not symmetric, and redundant rows have no minimum-norm "
                    "multipliers there. Remove the redundant constraints."
                )

    def with_control(self, control: Callable | None) -> "System":
        """A copy of this system with the control law ``u = control(q, qd, [t], [args])``
        (``None``: without one). The copy shares every other function and field."""
        if control is not None and self.actuation is None:
            raise ValueError(_CONTROL_WITHOUT_ACTUATION)
        law = wrap_state_function(control, "control law")
        return eqx.tree_at(lambda s: s.control, self, law, is_leaf=lambda x: x is None)

    # ----------------------------------------------------------------- structure and checks
    @property
    def is_constrained(self) -> bool:
        return self.holonomic is not None or self.velocity_constraints is not None

    def num_holonomic(self, q: Coordinates, t: RealScalarLike = 0.0, args: Args = None) -> int:
        """Number of holonomic constraints ``m_h`` (static, from shapes alone)."""
        if self.holonomic is None:
            return 0
        shape = jax.eval_shape(lambda x: _constraints.holonomic_residual(self, x, t, args), q)
        return shape.shape[0]

    def check(self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None) -> None:
        """Raise a clear error if shapes or output shapes are wrong (costs no computation)."""
        q = jnp.asarray(q)
        qd = jnp.asarray(qd)
        if q.ndim != 1:
            raise ValueError(f"q must be a 1-D array of generalized coordinates; got shape {q.shape}.")
        if qd.shape != q.shape:
            raise ValueError(f"q and qd must have the same shape (n,); got q {q.shape} and qd {qd.shape}.")
        if not jnp.issubdtype(q.dtype, jnp.floating) or not jnp.issubdtype(qd.dtype, jnp.floating):
            raise TypeError(f"q and qd must be floating point; got {q.dtype} and {qd.dtype}.")
        n = q.shape[0]
        t = jnp.asarray(t, dtype=q.dtype)

        def shape_of(fn, *state):
            return jax.eval_shape(lambda *s: fn(*s, t=t, args=args), *state).shape

        try:
            out = shape_of(self.lagrangian, q, qd)
        except Exception as error:
            # A per-member parameter that simulate_batch was not told about (args_axes) often
            # breaks L's shapes before it can return a non-scalar: name it if it is the cause.
            culprits = _array_args_behind(self.lagrangian, q, qd, t, args)
            if culprits:
                raise ValueError(
                    _batched_args_message(None, culprits, f"{type(error).__name__}: {error}")
                ) from error
            raise
        if out != ():
            culprits = _array_args_behind(self.lagrangian, q, qd, t, args)
            if culprits:
                raise ValueError(_batched_args_message(out, culprits))
            raise ValueError(
                f"The Lagrangian must return a scalar; it returned shape {out}. "
                "(Did you forget a sum, e.g. 0.5 * m * jnp.sum(qd**2)?)"
            )
        if self.holonomic is not None:
            out = shape_of(self.holonomic, q)
            if len(out) != 1:
                raise ValueError(
                    "The holonomic constraint function must return a 1-D array of shape (m,), one "
                    f"entry per constraint; it returned shape {out}. Wrap a single constraint as "
                    "jnp.array([f])."
                )
            bad = [i for i in self.unilateral if not 0 <= i < out[0]]
            if bad:
                raise ValueError(
                    f"unilateral={self.unilateral} names constraints {bad}, but the holonomic "
                    f"function returns only {out[0]} entries."
                )
            bad = [e.contact for e in self.friction if not e.contact < out[0]]
            if bad:
                raise ValueError(
                    f"friction names contact rows {bad}, but the holonomic function returns only "
                    f"{out[0]} entries."
                )
            bilateral = [e.contact for e in self.friction if e.contact not in self.unilateral]
            if bilateral:
                raise ValueError(
                    f"friction acts on contact rows {bilateral}, which are not unilateral: the "
                    "friction bound μλ_N needs a normal force λ_N ≥ 0, which only a unilateral "
                    "row keeps (it releases where λ_N would pull). Pass unilateral=... with "
                    "those rows."
                )
            for e in self.friction:
                tau = jax.eval_shape(lambda x, e=e: e.tangent(x, t=t, args=args), q).shape
                if tau != ():
                    raise ValueError(
                        f"A Coulomb tangent function must return a scalar; it returned shape {tau}."
                    )
        if self.velocity_constraints is not None:
            out = shape_of(self.velocity_constraints, q, qd)
            if len(out) != 1:
                raise ValueError(
                    "The velocity constraint function must return a 1-D array of shape (m,) "
                    f"(A(q, t) q̇ + b(q, t)); it returned shape {out}."
                )
        if self.dissipation is not None:
            out = shape_of(self.dissipation, q, qd)
            if out != ():
                raise ValueError(
                    f"The Rayleigh dissipation function must return a scalar; it returned shape {out}."
                )
        if self.forces is not None:
            out = shape_of(self.forces, q, qd)
            if out != (n,):
                raise ValueError(
                    f"The force function must return generalized forces of shape ({n},), like q; "
                    f"it returned shape {out}."
                )
        law = self.control
        if law is not None:
            u = jax.eval_shape(lambda x, v: law(x, v, t=t, args=args), q, qd)
            check_input_shape(self, q, qd, u, t, args, "The control law")

    # ----------------------------------------------------------------- mechanics at a state
    def _at_state(self, quantity, q, qd, t, args):
        q, qd = jnp.asarray(q), jnp.asarray(qd)
        self.check(q, qd, t, args)
        t = _mechanics.as_time(t, q)
        args = as_array_leaves(args, q.dtype if jnp.issubdtype(q.dtype, jnp.floating) else None)
        out = _evaluate_at_state(quantity, self, q, qd, t, args)
        if quantity in _SOLVED and self.mass_solve.checked:
            # RobustSolve: a failed state is NaN by design (jaxlag._mechanics.mass_solve).
            # The KKT solve turns a singular M or redundant rows into NaN: say so instead.
            out = check_state_result(self, quantity.__name__.strip("_"), out, q, qd, t, args)
        return out

    def lagrangian_value(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Scalar:
        """``L(q, q̇, t)``."""
        return self._at_state(_mechanics.lagrangian_value, q, qd, t, args)

    def mass_matrix(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Matrix:
        """``M = ∂²L/∂q̇²``, shape (n, n) (from the system's ``dynamics``)."""
        return self._at_state(_mechanics.mass_matrix, q, qd, t, args)

    def generalized_forces(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Vector:
        """``F = ∂L/∂q − (∂²L/∂q̇∂q) q̇ − ∂²L/∂q̇∂t − ∂R/∂q̇ + Q``, shape (n,)."""
        return self._at_state(_mechanics.generalized_forces, q, qd, t, args)

    def momenta(self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None) -> Vector:
        """``p = ∂L/∂q̇``."""
        return self._at_state(_mechanics.momenta, q, qd, t, args)

    def energy(self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None) -> Scalar:
        """Energy function ``h = q̇·∂L/∂q̇ − L``."""
        return self._at_state(_mechanics.energy, q, qd, t, args)

    def accelerations(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Vector:
        """``q̈`` from the (constrained) equations of motion. A unilateral constraint acts where
        it touches (``|f_i| ≤`` the default constraint tolerance) and does not separate, as at the
        start of [`simulate`][jaxlag.simulate]; elsewhere it is inactive (its ``λ_i = 0``)."""
        return self._at_state(_accelerations, q, qd, t, args)

    def multipliers(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, " m_h"]:
        """Holonomic multipliers ``λ`` (m_h,) in ``M q̈ = F + Jᵀλ + Aᵀμ``."""
        return self._at_state(_multipliers, q, qd, t, args)

    def velocity_multipliers(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, " m_v"]:
        """Velocity-constraint multipliers ``μ`` (m_v,) in ``M q̈ = F + Jᵀλ + Aᵀμ``."""
        return self._at_state(_velocity_multipliers, q, qd, t, args)

    def constraint_forces(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Vector:
        """Generalized constraint forces ``Qᶜ = Jᵀλ + Aᵀμ``, shape (n,)."""
        return self._at_state(_constraint_forces, q, qd, t, args)

    def constraint_residuals(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> tuple[Float[Array, " m_h"], Float[Array, " m_h"], Float[Array, " m_v"]]:
        """``(f, ḟ, g)``: holonomic position and velocity residuals, velocity-constraint residual."""
        return self._at_state(_constraints.constraint_residuals, q, qd, t, args)

    def dissipated_power(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Scalar:
        """``q̇·∂R/∂q̇``: power removed by dissipation."""
        return self._at_state(_mechanics.dissipated_power, q, qd, t, args)

    def input_power(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Scalar:
        """``q̇·(Q + Q_u)``: power delivered by external forces and the actuation."""
        return self._at_state(_mechanics.input_power, q, qd, t, args)

    def control_input(
        self, q: Coordinates, qd: Velocities, t: RealScalarLike = 0.0, args: Args = None
    ) -> Float[Array, " *k"]:
        """The input ``u = control(q, q̇, t)`` of the control law: a scalar or shape (k,)."""
        return self._at_state(_mechanics.control_input, q, qd, t, args)


def _wrap_actuation(fn: Callable | None) -> UserFunction | None:
    """Wrap ``Q_u(q, qd, u, [t], [args])``: three state arguments, ``t`` and ``args`` by keyword."""
    try:
        return _wrap_function(fn, "actuation function", 3)
    except TypeError as error:  # the shared messages name the state (q) of a 1-argument function
        text = (
            str(error)
            .replace("argument(s) (q)", "argument(s) (q, qd, u)")
            .replace("(q, t=t", "(q, qd, u, t=t")
        )
        raise TypeError(text) from None


_CONTROL_WITHOUT_ACTUATION = (
    "A control law needs an `actuation`: the generalized forces Q_u(q, qd, u, [t], [args]) "
    "through which its input u acts (M q̈ = F + Q_u + Jᵀλ), e.g. "
    "jl.System(L, actuation=lambda q, qd, u: jnp.stack([u, 0.0]), control=law)."
)


def check_input_shape(system, q, qd, u, t, args, what: str) -> None:
    """Raise if the input ``u`` (an array or shape-dtype struct) is not a scalar or a 1-D array,
    or if ``Q_u(q, q̇, u, t)`` is not of shape (n,) (shapes only, no computation)."""
    shape = tuple(u.shape)
    if len(shape) > 1:
        raise ValueError(
            f"{what} must give the input u as a scalar or a 1-D array (k,); it gave shape {shape}. "
            "Flatten a matrix of inputs (and index it so in the actuation)."
        )
    n = q.shape[0]
    u = jax.ShapeDtypeStruct(shape, q.dtype)  # the input is used in the state's dtype
    # Which size of u the actuation takes is the actuation's to say; when it refuses the one it
    # is given, the message names where that u came from (the control law, or linearize's u=).
    culprit = f"{what} gives u of shape {shape}, which the actuation function does not take: Q_u(q, qd, u)"
    try:
        out = jax.eval_shape(lambda x, v, w: system.actuation(x, v, w, t=t, args=args), q, qd, u).shape
    except Exception as error:
        raise ValueError(
            f"{culprit} raised {type(error).__name__}: {error}. Make {_lower(what)} give the "
            "input the actuation expects, or change the actuation."
        ) from error
    if out != (n,):
        raise ValueError(
            f"{culprit} must return the generalized forces of the input, shape ({n},) like q; "
            f"with u of shape {shape} it returned shape {out}. Make {_lower(what)} give the "
            "input the actuation expects, or change the actuation."
        )


def _lower(what: str) -> str:
    """``"The control law"`` as the object of a sentence."""
    return what[0].lower() + what[1:] if what.startswith("The ") else what


def _array_args_behind(fn, q, qd, t, args) -> list[tuple[tuple, tuple]]:
    """The array leaves of ``args`` that make ``fn`` non-scalar: those whose replacement by
    their first entry along the leading axis makes it return a scalar (``(path, shape)``)."""
    found = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(args):
        shape = getattr(leaf, "shape", ())
        if len(shape) == 0 or shape[0] == 0:
            continue

        def first(p, x, path=path):
            return x[0] if p == path else x

        try:
            one = jax.tree_util.tree_map_with_path(first, args)
            out = jax.eval_shape(lambda a, b: fn(a, b, t=t, args=one), q, qd).shape
        except Exception:  # noqa: BLE001 - only a diagnosis: a leaf whose removal breaks L is not it
            continue
        if out == ():
            found.append((path, tuple(shape)))
    return found


def _axes_hint(path) -> str:
    """``{'k': 0}`` for a path of dict keys (the ``args_axes`` that batches that leaf)."""
    text = "0"
    for key in reversed(path):
        if not isinstance(key, jax.tree_util.DictKey):
            return "a pytree prefix of args with 0 at that leaf"
        text = f"{{{key.key!r}: {text}}}"
    return text


def _batched_args_message(out, culprits, error: str | None = None) -> str:
    names = ", ".join(f"args{jax.tree_util.keystr(path)} (shape {shape})" for path, shape in culprits)
    path, shape = culprits[0]
    name = f"args{jax.tree_util.keystr(path)}"
    what = (
        f"The Lagrangian must return a scalar; it returned shape {out}"
        if error is None
        else f"The Lagrangian failed ({error})"
    )
    return (
        f"{what} because of {names}: with one entry of {name} it returns a scalar. If {name} "
        "holds one value per batch member of jl.simulate_batch, mark it batched there: "
        f"args_axes={_axes_hint(path)} (every "
        "other leaf stays shared; args_axes=0 batches them all). If it is a vector parameter "
        "of one system, index it or contract it in L (e.g. jnp.sum(k * q**2))."
    )


# Compiled once per (quantity, system, shapes): eager calls of the methods above are fast, and
# inside a user's jit the call is simply inlined.
@compilation.filter_jit
def _evaluate_at_state(quantity, system, q, qd, t, args):
    return quantity(system, q, qd, t, args)


def _solved(system, q, qd, t, args):
    """``(q̈, λ, μ)`` at a state, with the unilateral rows acting as at the start of a run
    (`jaxlag._checks.initial_activity`): one that touches (``|f_i| ≤`` the default constraint
    tolerance) and does not separate acts, any other is inactive (``λ_i = 0``)."""
    active = None
    if system.unilateral and system.holonomic is not None:
        active = initial_activity(system, q, qd, t, args, default_constraint_tolerance(q.dtype))
    return _kkt.accelerations_and_multipliers(system, q, qd, t, args, active=active)


def _accelerations(system, q, qd, t, args):
    return _solved(system, q, qd, t, args)[0]


def _multipliers(system, q, qd, t, args):
    return _solved(system, q, qd, t, args)[1]


def _velocity_multipliers(system, q, qd, t, args):
    return _solved(system, q, qd, t, args)[2]


def _constraint_forces(system, q, qd, t, args):
    _, lam, mu = _solved(system, q, qd, t, args)
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    return rows.T @ jnp.concatenate([lam, mu])


#: Quantities that come out of the KKT solve (checked for finiteness, see ``System._at_state``).
_SOLVED = (_accelerations, _multipliers, _velocity_multipliers, _constraint_forces)
