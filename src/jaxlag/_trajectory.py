"""``Trajectory``: the saved states of a simulation and the quantities derived from them."""

from typing import Any

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Bool, Float, Int

from . import _compile as compilation
from ._custom_types import Args, Multipliers, States, Times
from ._diagnosis import raise_if_failed
from ._errors import Failure
from ._events import EventLog
from ._mechanics import constraints as _constraints
from ._mechanics import friction as _friction
from ._mechanics import lagrangian as _mechanics
from ._system import System


def _constraint_forces(system, q, qd, t, args, active, modes):
    _, lam, mu, lam_t = _friction.solve_with_modes(system, q, qd, t, args, active=active, modes=modes)
    rows, _ = _constraints.constraint_rows(system, q, qd, t, args)
    forces = rows.T @ jnp.concatenate([lam, mu])
    if system.friction:
        forces = forces + _friction.tangent_terms(system, q, qd, t, args)[2].T @ lam_t
    return forces


def _kkt_output(index):
    # The KKT solve with each Coulomb contact in its saved stick/slip mode (without friction,
    # or modes None: jaxlag._mechanics.kkt's).
    def quantity(system, q, qd, t, args, active, modes):
        return _friction.solve_with_modes(system, q, qd, t, args, active=active, modes=modes)[index]

    return quantity


def _state_only(fn):
    return lambda system, q, qd, t, args, active, modes: fn(system, q, qd, t, args)


_QUANTITIES = {
    "accelerations": _kkt_output(0),
    "multipliers": _kkt_output(1),
    "velocity_multipliers": _kkt_output(2),
    "friction_forces": _kkt_output(3),
    "constraint_forces": _constraint_forces,
    "energy": _state_only(_mechanics.energy),
    "momenta": _state_only(_mechanics.momenta),
    "lagrangian": _state_only(_mechanics.lagrangian_value),
    "constraint_residuals": _state_only(_constraints.constraint_residuals),
    "dissipated_power": _state_only(_mechanics.dissipated_power),
    "input_power": _state_only(_mechanics.input_power),
    "controls": _state_only(_mechanics.control_input),
}


@compilation.filter_jit
def _evaluate(name: str, system_arrays, system_static, t, q, qd, args, active, modes=None):
    quantity = _QUANTITIES[name]

    def along_time(arrays, t_, q_, qd_, a_, active_, modes_):
        system = eqx.combine(arrays, system_static)
        return jax.vmap(lambda s, x, v, m, c: quantity(system, x, v, s, a_, m, c))(
            t_, q_, qd_, active_, modes_
        )

    fn = along_time
    for _ in range(q.ndim - 2):  # batch dimensions added by vmap-ing simulate
        fn = jax.vmap(fn)
    return fn(system_arrays, t, q, qd, args, active, modes)


class Trajectory(eqx.Module):
    """Saved states ``t`` (T,), ``q`` (T, n), ``qd`` (T, n) of a simulation.

    Derived quantities are computed on demand from the saved states, with the same system and
    parameters, under ``jit`` (inside a user's ``jit`` unused ones cost nothing). Batched
    trajectories (from ``jax.vmap`` of [`simulate`][jaxlag.simulate]) carry leading batch axes and
    their derived quantities do too.

    Multipliers and constraint forces are those of the exact constrained equations at the saved
    state (without any Baumgarte feedback term), with the convention ``M q̈ = F + Jᵀλ + Aᵀμ``.
    With Coulomb friction ([`Coulomb`][jaxlag.Coulomb]) they are those of the frictional solve in
    the stick/slip mode each contact was in at the saved time (`friction_modes`),
    ``M q̈ = F + Jᵀλ + Aᵀμ + Tᵀλ_t``; the tangential forces ``λ_t`` are
    `friction_forces` and ``constraint_forces`` includes ``Tᵀλ_t``.
    """

    t: Times
    q: States
    qd: States
    args: Args
    #: The solver's statistics (``num_steps``, ...; diffrax's, or the variational integrator's).
    #: With events or unilateral constraints: ``num_steps``, ``num_accepted_steps`` and
    #: ``num_rejected_steps`` summed over the segments, ``max_steps`` (per segment) and
    #: ``num_segments``, the segments that ran (the entries of ``events.kinds()``, and the
    #: crossings that directional conditions ignore).
    stats: dict[str, Any] | None
    result: diffrax.RESULTS | None
    # The system is split so that a Trajectory is a valid output of jax.jit / vmap: its arrays
    # (e.g. a neural-network Lagrangian's weights) are leaves, its functions static.
    system_arrays: System
    #: Holonomic activity mask (T, m_h) when unilateral constraints switch, else None.
    active: Bool[Array, "*batch times m_h"] | None
    #: [`EventLog`][jaxlag.EventLog] of the switches and events, or None.
    events: EventLog | None
    #: `jaxlag._errors.Failure`: how the run ended (``code`` 0: completed), or None.
    failure: Failure | None
    system_static: System = eqx.field(static=True)
    #: Friction mode (T, k) of each [`Coulomb`][jaxlag.Coulomb] contact at the saved times: 0
    #: sticking, +1 slipping with ``v_t > 0``, −1 with ``v_t < 0`` (0 also where the contact's
    #: normal row does not act, see `active`); None without friction.
    friction_modes: Int[Array, "*batch times k"] | None = None

    @classmethod
    def from_states(
        cls,
        system: System,
        t: Times,
        q: States,
        qd: States,
        args: Args,
        stats: dict[str, Any] | None = None,
        result: diffrax.RESULTS | None = None,
        active: Bool[Array, "*batch times m_h"] | None = None,
        events: EventLog | None = None,
        failure: Failure | None = None,
        modes: Int[Array, "*batch times k"] | None = None,
    ) -> "Trajectory":
        arrays, static = eqx.partition(system, eqx.is_array)
        return cls(t, q, qd, args, stats, result, arrays, active, events, failure, static, modes)

    def raise_if_failed(self) -> None:
        """Raise [`jaxlag.SimulationError`][jaxlag.SimulationError] with the numbers and a diagnosis if the
        run
        did not complete (for a trajectory computed with ``throw=False``, e.g. under ``jit``;
        call it outside the transformation). Batched trajectories name the failed members."""
        if self.failure is None:
            return
        batched = jnp.ndim(self.failure.code) > 0
        raise_if_failed(self.failure, None if batched else self.system, None if batched else self.args)

    @property
    def system(self) -> System:
        """The [`System`][jaxlag.System] that produced this trajectory."""
        return eqx.combine(self.system_arrays, self.system_static)

    def _get(self, name):
        return _evaluate(
            name,
            self.system_arrays,
            self.system_static,
            self.t,
            self.q,
            self.qd,
            self.args,
            self.active,
            self.friction_modes,
        )

    @property
    def accelerations(self) -> States:
        """``q̈`` (T, n)."""
        return self._get("accelerations")

    @property
    def multipliers(self) -> Multipliers:
        """Holonomic multipliers ``λ`` (T, m_h)."""
        return self._get("multipliers")

    @property
    def velocity_multipliers(self) -> Multipliers:
        """Velocity-constraint multipliers ``μ`` (T, m_v)."""
        return self._get("velocity_multipliers")

    @property
    def constraint_forces(self) -> States:
        """Generalized constraint forces ``Qᶜ = Jᵀλ + Aᵀμ`` (T, n) (``+ Tᵀλ_t`` with friction)."""
        return self._get("constraint_forces")

    @property
    def friction_forces(self) -> Float[Array, "*batch times k"]:
        """Tangential force ``λ_t`` (T, k) of each [`Coulomb`][jaxlag.Coulomb] contact, the
        coefficient of ``Tᵀ`` (``T = ∂τ/∂q``) in ``M q̈ = F + Jᵀλ + Tᵀλ_t``: the stick row's
        multiplier while sticking (``|λ_t| ≤ μ λ_N``), ``−μ sign(v_t) λ_N`` while slipping, 0
        where the normal row does not act. Shape (T, 0) without friction."""
        return self._get("friction_forces")

    @property
    def energy(self) -> Float[Array, "*batch times"]:
        """Energy function ``h = q̇·∂L/∂q̇ − L`` (T,)."""
        return self._get("energy")

    @property
    def momenta(self) -> States:
        """Generalized momenta ``p = ∂L/∂q̇`` (T, n)."""
        return self._get("momenta")

    @property
    def lagrangian(self) -> Float[Array, "*batch times"]:
        """``L`` along the trajectory (T,)."""
        return self._get("lagrangian")

    @property
    def constraint_residuals(
        self,
    ) -> tuple[
        Float[Array, "*batch times m_h"], Float[Array, "*batch times m_h"], Float[Array, "*batch times m_v"]
    ]:
        """``(f, ḟ, g)`` along the trajectory: shapes (T, m_h), (T, m_h), (T, m_v)."""
        return self._get("constraint_residuals")

    @property
    def dissipated_power(self) -> Float[Array, "*batch times"]:
        """``q̇·∂R/∂q̇`` (T,)."""
        return self._get("dissipated_power")

    @property
    def input_power(self) -> Float[Array, "*batch times"]:
        """``q̇·(Q + Q_u)`` (T,): power of the external forces and the actuation."""
        return self._get("input_power")

    @property
    def controls(self) -> Float[Array, "..."]:
        """The input ``u = control(q, q̇, t)`` of the system's control law: (T,) for a scalar
        input, (T, k) for a vector one (after any batch axes)."""
        return self._get("controls")
