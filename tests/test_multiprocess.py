"""simulate_batch over several processes: two JAX processes on this machine, joined by
``jax.distributed.initialize`` over loopback (127.0.0.1) with CPU collectives (gloo, the default
``jax_cpu_collectives_implementation`` of jax 0.10), each with 2 local CPU devices, so that
``jax.devices()`` lists 4 devices of which each process owns 2: the multi-controller setting of
several hosts, on one machine.

Each process runs the same ``simulate_batch(..., sharding="auto")`` (a mesh over the 4 global
devices), gathers the global result with ``multihost_utils.process_allgather`` and saves it; the
test compares both processes' results with the single-process, unsharded run of this process to
1e-12, events included. Three ways in: the same global batch in every process (B = 8, a multiple of
the device count, kept sharded), a batch that needs padding (B = 6, gathered on return), and global
``jax.Array`` s built from each process's own rows with ``jax.make_array_from_process_local_data``.

Equal local device counts are needed: JAX's own multi-process helpers (``device_put``'s equality
check across processes, ``process_allgather``) reshape ``jax.devices()`` to
``(process_count, local_device_count)``.
"""

import os
import pathlib
import socket
import subprocess
import sys
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np

import jaxlag as jl

jax.config.update("jax_enable_x64", True)

# Only guards against a hang (e.g. one process died and the other waits for it at a collective):
# the two processes take about 30 s together on this 2-core machine; load may stretch that a lot.
HANG_GUARD_SECONDS = 900
PROCESSES, LOCAL_DEVICES = 2, 2

_WORKER = textwrap.dedent(
    """
    import sys
    import jax

    process_id, port, out = int(sys.argv[1]), int(sys.argv[2]), sys.argv[3]
    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_platforms", "cpu")
    jax.config.update("jax_num_cpu_devices", {local})
    jax.config.update("jax_cpu_collectives_implementation", "gloo")
    jax.distributed.initialize(coordinator_address=f"127.0.0.1:{{port}}", num_processes={processes},
                               process_id=process_id, initialization_timeout=600)

    import jax.numpy as jnp
    import numpy as np
    from jax.experimental import multihost_utils
    import jaxlag as jl

    assert jax.process_count() == {processes} and jax.process_index() == process_id
    assert jax.device_count() == {processes} * {local} and jax.local_device_count() == {local}

    def lagrangian(q, qd, args):             # particle outside a sphere, polar (r, θ) from the top
        r, th = q
        rd, thd = qd
        return 0.5 * (rd**2 + r**2 * thd**2) - args["g"] * r * jnp.cos(th)

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]),
                       unilateral=0)         # r − R ≥ 0: it lets go
    ts = jnp.linspace(0.0, 1.6, 9)
    theta0 = jnp.linspace(0.2, 0.55, 8)
    q0 = jnp.stack([jnp.full_like(theta0, 2.0), theta0], axis=1)
    g = jnp.linspace(9.0, 10.0, 8)
    options = dict(events=jl.Events(max_segments=3), sharding="auto", args_axes={{"g": 0, "R": None}})

    def gather(traj):
        return {{name: np.asarray(multihost_utils.process_allgather(x, tiled=True)) for name, x in
                (("q", traj.q), ("qd", traj.qd), ("time", traj.events.time),
                 ("kind", traj.events.kind))}}

    same = jl.simulate_batch(system, q0, jnp.zeros(2), ts, args={{"g": g, "R": 2.0}}, **options)
    assert not same.q.is_fully_addressable and same.q.sharding.spec[0] == "batch"
    assert [s.data.shape for s in same.q.addressable_shards] == [(2, 9, 2)] * {local}

    padded = jl.simulate_batch(system, q0[:6], jnp.zeros(2), ts, args={{"g": g[:6], "R": 2.0}},
                               **options)    # 6 members padded to 8 and cut back on return
    assert padded.q.shape == (6, 9, 2)

    sharding = jl.batch_sharding("auto")
    rows = slice(4 * process_id, 4 * process_id + 4)   # this process's own members
    own_q0 = jax.make_array_from_process_local_data(sharding, np.asarray(q0[rows]))
    own_g = jax.make_array_from_process_local_data(sharding, np.asarray(g[rows]))
    assert own_q0.shape == (8, 2)
    own = jl.simulate_batch(system, own_q0, jnp.zeros(2), ts, args={{"g": own_g, "R": 2.0}}, **options)

    results = {{f"{{way}}_{{name}}": value for way, traj in (("same", same), ("padded", padded),
                                                          ("own", own))
               for name, value in gather(traj).items()}}
    np.savez(out, **results)
    print("MULTIPROCESS-OK", process_id)
    """
).format(processes=PROCESSES, local=LOCAL_DEVICES)


def _free_loopback_port():
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


def _run_processes(tmp_path):
    env = dict(os.environ)
    env["JAX_PLATFORMS"] = "cpu"
    flags = [f for f in env.get("XLA_FLAGS", "").split() if "host_platform_device_count" not in f]
    env["XLA_FLAGS"] = " ".join(flags)
    source = str(pathlib.Path(jl.__file__).resolve().parents[1])  # the jaxlag under test
    env["PYTHONPATH"] = os.pathsep.join([source] + [p for p in [env.get("PYTHONPATH")] if p])
    port = _free_loopback_port()
    logs = [open(tmp_path / f"process{i}.log", "w+") for i in range(PROCESSES)]
    processes = [
        subprocess.Popen(
            [sys.executable, "-c", _WORKER, str(i), str(port), str(tmp_path / f"process{i}.npz")],
            env=env,
            stdout=logs[i],
            stderr=subprocess.STDOUT,
        )
        for i in range(PROCESSES)
    ]
    start = time.monotonic()
    try:
        # When one process fails the other may wait for it forever at a collective: stop it.
        while any(p.poll() is None for p in processes):
            if any(p.returncode not in (None, 0) for p in processes):
                break
            if time.monotonic() - start > HANG_GUARD_SECONDS:
                break
            time.sleep(0.5)
    finally:
        for p in processes:
            if p.poll() is None:
                p.kill()
                p.wait()
    outputs = []
    for log in logs:
        log.seek(0)
        outputs.append(log.read())
        log.close()
    report = "\n".join(
        f"--- process {i} (exit {p.returncode}):\n{out[-4000:]}"
        for i, (p, out) in enumerate(zip(processes, outputs))
    )
    assert all(p.returncode == 0 for p in processes), report
    assert all(f"MULTIPROCESS-OK {i}" in out for i, out in enumerate(outputs)), report
    return [dict(np.load(tmp_path / f"process{i}.npz")) for i in range(PROCESSES)]


def test_two_processes_with_cpu_collectives_equal_the_single_process_batch(tmp_path):
    results = _run_processes(tmp_path)

    def lagrangian(q, qd, args):
        r, th = q
        rd, thd = qd
        return 0.5 * (rd**2 + r**2 * thd**2) - args["g"] * r * jnp.cos(th)

    system = jl.System(lagrangian, holonomic=lambda q, args: jnp.array([q[0] - args["R"]]), unilateral=0)
    ts = jnp.linspace(0.0, 1.6, 9)
    theta0 = jnp.linspace(0.2, 0.55, 8)
    q0 = jnp.stack([jnp.full_like(theta0, 2.0), theta0], axis=1)
    g = jnp.linspace(9.0, 10.0, 8)
    single = jl.simulate_batch(
        system,
        q0,
        jnp.zeros(2),
        ts,
        args={"g": g, "R": 2.0},
        args_axes={"g": 0, "R": None},
        events=jl.Events(max_segments=3),
    )
    expected = {"q": single.q, "qd": single.qd, "time": single.events.time, "kind": single.events.kind}
    # Each member lets go of the sphere where cos θ = (2/3) cos θ0, whatever g.
    assert np.all(np.asarray(single.events.kind[:, 0]) == 1)
    np.testing.assert_allclose(single.events.q[:, 0, 1], np.arccos(2 / 3 * np.cos(theta0)), atol=1e-8)

    for process, result in enumerate(results):
        for way, members in (("same", 8), ("padded", 6), ("own", 8)):
            for name, value in expected.items():
                got = result[f"{way}_{name}"]
                assert got.shape == value[:members].shape, (process, way, name, got.shape)
                if name == "kind":
                    np.testing.assert_array_equal(got, value[:members], err_msg=f"{process} {way}")
                else:  # same arithmetic on every device: agreement to round-off, inf where unused
                    np.testing.assert_allclose(
                        got, value[:members], rtol=0, atol=1e-12, err_msg=f"process {process}, {way}, {name}"
                    )
