"""jaxlag.inputs: time tables (zero-order hold, piecewise linear, natural cubic spline).

Checked against NumPy/SciPy interpolation, against the closed-form motion of a driven harmonic
oscillator q̈ = −ω²q + u(t) (exact on every interval of the table), against central finite
differences (exact here: the final state is linear in the table values, the loss quadratic), and
under jit and vmap.
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl
from jaxlag import _inputs, inputs

W = 2.0  # ω
TABLE_TS = np.linspace(0.0, 5.0, 11)
TABLE_VALUES = np.random.default_rng(0).normal(size=(3, 11))
Q0, QD0 = np.array([0.3]), np.array([0.0])


def _lagrangian(q, qd):
    return 0.5 * jnp.sum(qd**2) - 0.5 * W**2 * jnp.sum(q**2)


DRIVEN = jl.System(_lagrangian, forces=lambda q, qd, t, args: jnp.reshape(args["u"](t), (1,)))


def closed_form(t_query, q0, v0, ts, us, kind):
    """q(t) of q̈ = −ω²q + u(t) for u held ("zoh") or linear ("linear") between the samples (and
    held after the last): on each interval u = α + βs, q = (α + βs)/ω² + c₁ cos ωs + c₂ sin ωs."""
    out = []
    for end in t_query:
        q, v = q0, v0
        for i in range(len(ts)):
            right = ts[i + 1] if i + 1 < len(ts) else np.inf
            s = min(end, right) - ts[i]
            alpha, beta = us[i], 0.0
            if kind == "linear" and i + 1 < len(ts):
                beta = (us[i + 1] - us[i]) / (ts[i + 1] - ts[i])
            c1, c2 = q - alpha / W**2, (v - beta / W**2) / W
            q, v = (
                (alpha + beta * s) / W**2 + c1 * np.cos(W * s) + c2 * np.sin(W * s),
                beta / W**2 - c1 * W * np.sin(W * s) + c2 * W * np.cos(W * s),
            )
            if end <= right:
                break
        out.append(q)
    return np.array(out)


def test_interpolation_against_numpy():
    scipy_interpolate = pytest.importorskip("scipy.interpolate")
    ts = np.array([0.0, 0.4, 1.0, 1.5, 2.5])
    values = np.random.default_rng(1).normal(size=(5, 2))
    # samples, between samples, and outside [t0, tN] (end values held)
    t = np.concatenate([ts, [0.1, 0.7, 1.2, 2.0, 2.49], [-1.0, 3.0]])
    inside = np.clip(t, ts[0], ts[-1])
    hold = values[np.clip(np.searchsorted(ts, t, side="right") - 1, 0, 4)]
    linear = np.stack([np.interp(t, ts, values[:, j]) for j in range(2)], axis=1)
    spline = scipy_interpolate.CubicSpline(ts, values, bc_type="natural")(inside)
    for cls, expected in (
        (inputs.ZeroOrderHold, hold),
        (inputs.PiecewiseLinear, linear),
        (inputs.CubicSpline, spline),
    ):
        table = cls(ts, values)
        eager = np.stack([np.asarray(table(x)) for x in t])
        np.testing.assert_allclose(eager, expected, rtol=0, atol=1e-14, err_msg=cls.__name__)
        np.testing.assert_allclose(jax.jit(jax.vmap(table))(t), expected, rtol=0, atol=1e-14)
        # (N,) values give scalars
        scalar = cls(ts, values[:, 0])
        assert scalar(0.3).shape == ()
        np.testing.assert_allclose(jax.vmap(scalar)(t), expected[:, 0], rtol=0, atol=1e-14)
    # right-continuous hold: at a sample time the new value holds, just before it the old one
    hold_table = inputs.ZeroOrderHold(ts, values[:, 0])
    assert float(hold_table(np.nextafter(0.4, 0.0))) == values[0, 0]
    assert float(hold_table(0.4)) == values[1, 0]
    # natural spline: u'' = 0 at both ends, C² at the knots
    spline_table = inputs.CubicSpline(ts, values[:, 0])
    second = jax.grad(jax.grad(spline_table))
    assert abs(float(second(ts[0]))) < 1e-12 and abs(float(second(np.nextafter(ts[-1], 0.0)))) < 1e-9
    for knot in ts[1:-1]:
        left, right = second(np.nextafter(knot, -np.inf)), second(knot)
        np.testing.assert_allclose(left, right, rtol=0, atol=1e-9)


def test_oscillator_closed_form_and_breakpoints():
    """q(t) matches the piecewise closed form to 1e-9; with the breakpoints handed to the solver
    (a table in args) the zero-order hold takes far fewer steps than the same table hidden in a
    closure, which the controller must find by rejected steps."""
    save = np.linspace(0.0, 6.0, 13)
    values = TABLE_VALUES[0]
    for cls, kind in ((inputs.ZeroOrderHold, "zoh"), (inputs.PiecewiseLinear, "linear")):
        expected = closed_form(save, Q0[0], QD0[0], TABLE_TS, values, kind)
        traj = jl.simulate(DRIVEN, Q0, QD0, save, args={"u": cls(TABLE_TS, values)})
        np.testing.assert_allclose(traj.q[:, 0], expected, rtol=0, atol=1e-9, err_msg=cls.__name__)
        if cls is inputs.ZeroOrderHold:
            hidden = cls(TABLE_TS, values)
            closure = jl.System(_lagrangian, forces=lambda q, qd, t: jnp.reshape(hidden(t), (1,)))
            blind = jl.simulate(closure, Q0, QD0, save)
            assert int(traj.stats["num_steps"]) * 2 < int(blind.stats["num_steps"])
            assert int(traj.stats["num_rejected_steps"]) < 20 < int(blind.stats["num_rejected_steps"])
            # the explicit path gives the same steps as the automatic one
            controller = inputs.with_breakpoints(diffrax.PIDController(rtol=1e-10, atol=1e-10), hidden)
            told = jl.simulate(closure, Q0, QD0, save, stepsize_controller=controller)
            assert int(told.stats["num_steps"]) == int(traj.stats["num_steps"])
            np.testing.assert_allclose(told.q[:, 0], expected, rtol=0, atol=1e-9)


@pytest.mark.parametrize("cls", [inputs.ZeroOrderHold, inputs.CubicSpline])
def test_gradient_wrt_table_values(cls):
    """jax.grad through simulate w.r.t. the values vs central differences (exact for this
    quadratic loss up to the solver's tolerance)."""
    n = 8 if cls is inputs.ZeroOrderHold else 6
    ts, values = TABLE_TS[:n], TABLE_VALUES[1, :n]

    def loss(v):
        traj = jl.simulate(DRIVEN, Q0, QD0, np.array([0.0, 6.0]), args={"u": cls(ts, v)})
        return traj.q[-1, 0] ** 2 + traj.qd[-1, 0] ** 2

    grad = jax.grad(loss)(values)
    h = 1e-2
    fd = np.array([(loss(values + h * e) - loss(values - h * e)) / (2 * h) for e in np.eye(n)])
    assert np.max(np.abs(grad - fd)) / np.max(np.abs(fd)) < 1e-6


def test_batch_of_tables():
    """A batch of tables (vmapped construction: values and ts get a leading axis) through
    simulate_batch and through jit(vmap(simulate)) equals simulating them one by one; each
    member steps onto its own breakpoints."""
    save = np.linspace(0.0, 6.0, 4)
    values = TABLE_VALUES[:2]
    tables = jax.vmap(lambda v: inputs.ZeroOrderHold(TABLE_TS, v))(values)
    assert tables.ts.shape == tables.values.shape == (2, 11)
    batch = jl.simulate_batch(DRIVEN, Q0, QD0, save, args={"u": tables}, args_axes=0)
    mapped = jax.jit(
        jax.vmap(
            lambda v: jl.simulate(DRIVEN, Q0, QD0, save, args={"u": inputs.ZeroOrderHold(TABLE_TS, v)}).q
        )
    )(values)
    for i, v in enumerate(values):
        expected = closed_form(save, Q0[0], QD0[0], TABLE_TS, v, "zoh")
        np.testing.assert_allclose(batch.q[i, :, 0], expected, rtol=0, atol=1e-9)
        np.testing.assert_allclose(mapped[i, :, 0], expected, rtol=0, atol=1e-9)
    assert np.all(np.asarray(batch.stats["num_rejected_steps"]) < 20)


def test_bad_tables():
    ts = np.array([0.0, 1.0, 1.0, 2.0])
    with pytest.raises(ValueError, match=r"strictly increasing; ts\[2\] = 1.0 does not exceed ts\[1\]"):
        inputs.ZeroOrderHold(ts, np.zeros(4))
    with pytest.raises(ValueError, match=r"ts\[1\] = nan is not finite"):
        inputs.PiecewiseLinear(np.array([0.0, np.nan]), np.zeros(2))
    with pytest.raises(
        ValueError, match=r"shape \(3, \.\.\.\) for ts of shape \(3,\); got values of shape \(2, 3\)"
    ):
        inputs.CubicSpline(np.arange(3.0), np.zeros((2, 3)))
    with pytest.raises(ValueError, match=r"values\[1\] = \[ 0. nan\] is not finite"):
        inputs.PiecewiseLinear(np.arange(2.0), np.array([[0.0, 0.0], [0.0, np.nan]]))
    with pytest.raises(ValueError, match="1-D array of sample times; got shape"):
        inputs.ZeroOrderHold(np.zeros((2, 2)), np.zeros(2))
    with pytest.raises(ValueError, match="at least 2 samples"):
        inputs.CubicSpline(np.zeros(1), np.zeros(1))
    assert float(inputs.ZeroOrderHold([0.0], [2.0])(5.0)) == 2.0  # one sample: a constant
    # traced: the same checks, compiled in
    build = jax.jit(lambda t, v: inputs.PiecewiseLinear(t, v)(0.5))
    with pytest.raises(Exception, match="finite and strictly increasing"):
        build(jnp.array([0.0, 1.0, 0.5]), jnp.zeros(3))
    with pytest.raises(Exception, match="values` must be finite"):
        build(jnp.array([0.0, 1.0, 2.0]), jnp.array([0.0, jnp.inf, 0.0]))
    # with_breakpoints: adaptive controllers only, and at least one table
    table = inputs.ZeroOrderHold(ts[:2], np.zeros(2))
    with pytest.raises(TypeError, match="adaptive step-size controller"):
        inputs.with_breakpoints(diffrax.ConstantStepSize(), table)
    with pytest.raises(ValueError, match="no time table"):
        inputs.with_breakpoints(diffrax.PIDController(rtol=1e-6, atol=1e-6), {"k": 1.0})


def test_with_breakpoints_merges():
    hold = inputs.ZeroOrderHold(np.array([0.0, 1.0]), np.zeros(2))
    line = inputs.PiecewiseLinear(np.array([0.5, 2.0]), np.zeros(2))
    base = diffrax.PIDController(rtol=1e-6, atol=1e-6, jump_ts=[3.0], step_ts=[4.0])
    merged = inputs.with_breakpoints(base, {"u": hold, "w": line})
    assert isinstance(merged.controller, diffrax.PIDController)
    np.testing.assert_array_equal(merged.jump_ts, [0.0, 1.0, 3.0])
    np.testing.assert_array_equal(merged.step_ts, [0.5, 2.0, 4.0])
    # a float64 table drives a float32 simulation: the breakpoints take the time's dtype (diffrax
    # refuses jump_ts of another dtype)
    save32 = np.linspace(0.0, 6.0, 4).astype(np.float32)
    traj = jl.simulate(DRIVEN, Q0.astype(np.float32), QD0.astype(np.float32), save32, args={"u": hold})
    assert traj.q.dtype == np.float32 and np.all(np.isfinite(traj.q))
    closure = jl.System(_lagrangian, forces=lambda q, qd, t: jnp.stack([hold(t)]).astype(q.dtype))
    controller = inputs.with_breakpoints(diffrax.PIDController(rtol=1e-5, atol=1e-5), hold)
    told = jl.simulate(
        closure, Q0.astype(np.float32), QD0.astype(np.float32), save32, stepsize_controller=controller
    )
    np.testing.assert_allclose(told.q, traj.q, rtol=0, atol=1e-4)
    # a fixed step is left as it is by simulate
    fixed = diffrax.ConstantStepSize()
    assert _inputs.controller_for_args(fixed, {"u": hold}, jnp.float64) is fixed
    # the breakpoints carry no gradient
    grad = jax.grad(lambda t: jnp.sum(inputs.ZeroOrderHold(t, np.zeros(2)).breakpoints))(
        jnp.array([0.0, 1.0])
    )
    np.testing.assert_array_equal(grad, 0.0)
    assert eqx.is_array(hold.ts)
