"""With the opt-in persistent cache, a second process compiles none of jaxlag's programs.

JAX's persistent cache keeps no program that holds a host callback (``eqx.error_if``, diffrax's
run-time checks of ``SaveAt(ts=...)``), so this is a property of the programs jaxlag builds
when called eagerly: each must be free of host callbacks. Two fresh processes run the same
script on one cache directory; in the second, every compile request must be a cache hit
(``jax.monitoring``'s ``compile_requests_use_cache`` and ``cache_hits`` events). The script:
the README example, its first ``jax.grad``, a ``simulate_batch`` and a constant-step solve with
``dt0`` and a bouncing ball (the segment loop of events), then the other entry points: a
linearization (``jl.analysis.linearize``), an equilibrium (``jl.analysis.equilibrium``) and the
acceleration loss of a learned Lagrangian (``jaxlag.learned``) with its gradient, and a variational
integration (``jl.simulate_variational``)."""

import json
import os
import subprocess
import sys
import textwrap

_SCRIPT = textwrap.dedent(
    """
    import json, sys
    import jax
    jax.config.update("jax_enable_x64", True)
    counts = {"requests": 0, "hits": 0}
    def count(event, **kwargs):
        if event == "/jax/compilation_cache/compile_requests_use_cache":
            counts["requests"] += 1
        elif event == "/jax/compilation_cache/cache_hits":
            counts["hits"] += 1
    jax.monitoring.register_event_listener(count)
    import jax.numpy as jnp
    import jaxlag as jl
    jl.enable_compilation_cache(sys.argv[1])

    def lagrangian(q, qd, args):  # the README's particle on a sphere, in polar coordinates
        r, th = q
        rd, thd = qd
        return 0.5 * args["m"] * (rd**2 + r**2 * thd**2) - args["m"] * args["g"] * r * jnp.cos(th)

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]))
    args = {"m": 1.0, "g": 9.81, "R": 2.0}
    q0, qd0 = jnp.array([2.0, 0.1]), jnp.zeros(2)
    traj = jl.simulate(system, q0, qd0, jnp.linspace(0, 2, 201), args=args)
    jax.block_until_ready(traj.multipliers)
    loss = lambda a: jnp.sum(jl.simulate(system, q0, qd0, jnp.linspace(0, 1, 11), args=a).q[:, 1] ** 2)
    jax.block_until_ready(jax.grad(loss)(args))
    pendulum = jl.System(lambda q, qd, args: 0.5 * qd[0] ** 2 + args["g"] * jnp.cos(q[0]))
    batch = jl.simulate_batch(pendulum, jnp.linspace(0.1, 1.0, 8)[:, None], jnp.zeros(1),
                              jnp.linspace(0, 2, 21), args={"g": 9.81})
    jax.block_until_ready(batch.q)
    import diffrax
    fixed = jl.simulate(pendulum, jnp.array([0.5]), jnp.zeros(1), jnp.linspace(0, 1, 11), args={"g": 9.81},
                        solver=jl.RK4(), stepsize_controller=diffrax.ConstantStepSize(), dt0=0.01)
    jax.block_until_ready(fixed.q)
    ball = jl.System(lambda q, qd: 0.5 * qd[0] ** 2 - 9.81 * q[0], lambda q: q[:1],
                     unilateral=jl.Unilateral(0, restitution=0.8))
    bounces = jl.simulate(ball, jnp.array([1.0]), jnp.zeros(1), jnp.linspace(0.0, 2.0, 51),
                          events=jl.Events(max_segments=16))
    jax.block_until_ready(bounces.q)
    # The other entry points: a linearization, an equilibrium, a learned model's loss and grad.
    upright = jl.analysis.linearize(pendulum, jnp.array([jnp.pi]), jnp.zeros(1), args={"g": 9.81})
    jax.block_until_ready(upright.state_matrix)
    rest = jl.analysis.equilibrium(pendulum, jnp.array([3.0]), jnp.zeros(1), args={"g": 9.81})
    jax.block_until_ready(rest.q)
    import equinox as eqx
    from jaxlag import learned as jll
    model = jll.DeLaN(1, 16, 2, key=jax.random.PRNGKey(0))
    q = jnp.linspace(-1.0, 1.0, 8)[:, None]
    data = jll.StateData(q, jnp.linspace(-0.5, 0.5, 8)[:, None], -9.81 * jnp.sin(q))
    value, grads = eqx.filter_value_and_grad(lambda m: jll.AccelerationLoss()(m, data).value)(model)
    jax.block_until_ready((value, grads))
    variational = jl.simulate_variational(pendulum, jnp.array([0.5]), jnp.zeros(1), dt=0.01, num_steps=20,
                                          args={"g": 9.81})
    jax.block_until_ready(variational.q)
    print("COUNTS " + json.dumps(counts))
    """
)


def _run(cache_dir) -> dict:
    env = {k: v for k, v in os.environ.items() if not k.startswith("JAX_COMPILATION_CACHE")}
    out = subprocess.run(
        [sys.executable, "-c", _SCRIPT, str(cache_dir)], capture_output=True, text=True, env=env, timeout=900
    )
    assert out.returncode == 0, out.stderr[-3000:]
    line = next(line for line in out.stdout.splitlines() if line.startswith("COUNTS "))
    return json.loads(line[len("COUNTS ") :])


def test_second_process_compiles_nothing(tmp_path):
    cache = tmp_path / "cache"
    first = _run(cache)
    assert first["requests"] > 10  # the script compiles jaxlag's programs ...
    second = _run(cache)
    assert second["requests"] == first["requests"]
    assert second["hits"] == second["requests"], second  # ... and the second process none of them
