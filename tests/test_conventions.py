"""One calling convention for every user function: state positionally, t and args by keyword."""

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import jaxlag as jl

Q = jnp.array([0.3])
QD = jnp.array([0.2])


@pytest.mark.parametrize(
    "lagrangian",
    [
        lambda q, qd: 0.5 * qd[0] ** 2 - 2.0 * q[0] ** 2,
        lambda q, qd, args: 0.5 * qd[0] ** 2 - args * q[0] ** 2,
        lambda q, qd, t: 0.5 * qd[0] ** 2 - (2.0 + 0 * t) * q[0] ** 2,
        lambda q, qd, t, args: 0.5 * qd[0] ** 2 - args * q[0] ** 2,
        lambda q, qd, args, t: 0.5 * qd[0] ** 2 - args * q[0] ** 2,
        lambda q, qd, *, t, args: 0.5 * qd[0] ** 2 - args * q[0] ** 2,
        lambda q, qd, **kwargs: 0.5 * qd[0] ** 2 - kwargs["args"] * q[0] ** 2,
    ],
)
def test_every_signature_form_gives_the_same_mechanics(lagrangian):
    system = jl.System(lagrangian)
    np.testing.assert_allclose(system.accelerations(Q, QD, 0.0, 2.0), [-4.0 * 0.3], rtol=1e-14)


def test_time_is_passed_to_time_dependent_functions():
    system = jl.System(lambda q, qd, t: 0.5 * qd[0] ** 2 + t * q[0])
    np.testing.assert_allclose(system.accelerations(Q, QD, 1.5), [1.5])


def test_diffrax_order_is_rejected_with_a_pointer():
    with pytest.raises(TypeError, match="state first"):
        jl.System(lambda t, q, qd, args: 0.0)


def test_unknown_required_parameter_is_rejected():
    with pytest.raises(TypeError, match="cannot fill"):
        jl.System(lambda q, qd, mass: 0.5 * mass * qd[0] ** 2)


def test_too_few_positional_parameters():
    with pytest.raises(TypeError, match="positional"):
        jl.System(lambda q: 0.0)
    with pytest.raises(TypeError, match="positional"):
        jl.System(lambda q, qd: 0.5 * qd @ qd, holonomic=lambda: jnp.zeros(1))


def test_parameters_with_defaults_are_left_alone():
    system = jl.System(lambda q, qd, scale=3.0: 0.5 * scale * qd[0] ** 2 - q[0] ** 2)
    np.testing.assert_allclose(system.accelerations(Q, QD), [-2 * 0.3 / 3.0], rtol=1e-14)


class LearnedPotential(eqx.Module):
    """A Lagrangian that is itself a pytree of arrays (as a neural network would be)."""

    stiffness: jax.Array

    def __call__(self, q, qd):
        return 0.5 * qd @ qd - 0.5 * self.stiffness * q @ q


def test_module_lagrangian_is_differentiated_through():
    def final_position(model):
        return jl.simulate(jl.System(model), [1.0], [0.0], jnp.array([0.0, 1.0])).q[-1, 0]

    grads = eqx.filter_grad(final_position)(LearnedPotential(jnp.array(4.0)))
    # q(t) = cos(√k t): ∂q(1)/∂k = −sin(√k) / (2√k) at k = 4.
    # Tolerance: default rtol 1e-10 of the adaptive solve, propagated through the adjoint.
    np.testing.assert_allclose(grads.stiffness, -np.sin(2.0) / 4.0, rtol=1e-7)


def test_host_values_become_jax_arrays_without_compiling():
    """as_jax_array / as_array_leaves give what jnp.asarray gives (value, dtype, weak type) for
    host values, and compile no device program for them (jnp.asarray compiles a copy per shape
    of a NumPy array and a conversion per dtype change)."""
    from test_batch import CompileCounter

    from jaxlag._conventions import as_array_leaves, as_jax_array

    with CompileCounter() as compiles:
        shape = (3, 7)  # a shape no other test converts
        cases = [
            (np.linspace(0.0, 1.0, 21).reshape(shape), None),
            (np.arange(21).reshape(shape), None),
            (np.arange(21, dtype=np.float32).reshape(shape), jnp.float64),
            ([1.5, 2.5, 3.5, 4.5, 5.5, 6.5, 7.5], None),
            (2.75, jnp.float64),
        ]
        for value, dtype in cases:
            got = as_jax_array(value, dtype)
            assert isinstance(got, jax.Array)
            assert got.dtype == np.asarray(value, dtype).dtype
            assert not jax.typeof(got).weak_type
            np.testing.assert_array_equal(got, np.asarray(value, dtype))
        leaves = as_array_leaves({"g": 9.81, "k": np.float32(2.0), "n": 3})
        assert leaves["g"].dtype == jnp.float64 and leaves["k"].dtype == jnp.float32
        assert leaves["n"] == 3 and isinstance(leaves["n"], int)
        assert compiles.count == 0


def test_as_array_leaves_leaves_non_array_leaves_of_modules_alone():
    """An eqx.nn.MLP in args: its arrays keep their dtype, its activation function (not an
    array) is the same object, so the module still runs and partitions as before."""
    import equinox as eqx

    from jaxlag._conventions import as_array_leaves

    net = eqx.nn.MLP(2, 1, 3, 1, activation=jax.nn.softplus, key=jax.random.PRNGKey(0), dtype=jnp.float32)
    out = as_array_leaves({"net": net, "g": 9.81}, jnp.float64)
    assert out["net"].activation is net.activation
    assert out["net"].layers[0].weight.dtype == jnp.float32 and out["g"].dtype == jnp.float64
    np.testing.assert_array_equal(out["net"](jnp.ones(2, jnp.float32)), net(jnp.ones(2, jnp.float32)))
