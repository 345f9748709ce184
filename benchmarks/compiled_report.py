"""What XLA compiled for jaxlag's right-hand side: a quick look when a ratio is poor.

For each benchmark system, compiles jaxlag's vector field at one state (and the whole
fixed-step simulation) and counts what matters on CPU: LAPACK custom calls (each costs about
0.5 µs of call overhead however small the matrix), ``while`` loops, ``reduce-window`` (what
``jnp.cumsum`` lowers to on CPU: O(n²) per call), fusions (one kernel launch each), and any
``pred[n, n]`` carried by a ``while`` loop: the identity basis of the mass-matrix ``jvp``
hoisted out of diffrax's stage loop, after which the ``n × n`` tangent kernels run several
times slower.

Run: ``python -m benchmarks.compiled_report`` from the repository root.
"""

from __future__ import annotations

import re

import jax

import jaxlag as jl
from jaxlag._mechanics import kkt as kkt

from . import bench_constrained as bc
from . import bench_unconstrained as bu
from . import common  # first: pins the core and sets XLA_FLAGS before jax is imported


def summary(text: str, n: int) -> str:
    calls = sorted(set(re.findall(r'custom_call_target="([^"]+)"', text)) - {"xla_ffi_python_cpu_callback"})
    carried = sum(f"pred[{n},{n}]" in line for line in text.splitlines() if " while(" in line)
    return (
        f"fusions {text.count('fusion(')}, while {text.count(' while(')}, "
        f"reduce-window {text.count('reduce-window(')}, dot {text.count(' dot(')}, "
        f"LAPACK {', '.join(calls) or '-'}, while loops carrying pred[{n},{n}]: {carried}"
    )


def report(name, system, q, qd, constrained):
    def rhs(q, qd):
        if constrained:
            return kkt.accelerations_and_multipliers(system, q, qd, 0.0, None)[0]
        return jl.EquationsOfMotion(system)(0.0, (q, qd), None)[1]

    n = q.shape[0]
    one = jax.jit(rhs).lower(q, qd).compile().as_text()
    kwargs = {"projection": None} if constrained else {}
    simulation = bu.with_jaxlag(system, checks=jl.Checks(initial_state=False), **kwargs)
    whole = jax.jit(simulation).lower(q, qd).compile().as_text()
    print(f"{name}")
    print(f"  one right-hand side : {summary(one, n)}")
    print(f"  whole simulation    : {summary(whole, n)}")


def main():
    print(common.environment_line())
    for n in bu.CHAIN_SIZES:
        q, qd = bu.chain_initial_state(n)
        report(f"chain N={n}, L by cumsum", jl.System(bu.chain_lagrangian), q, qd, False)
        report(
            f"chain N={n}, L = ½q̇ᵀM(q)q̇ − V", jl.System(bu.make_chain_quadratic_lagrangian(n)), q, qd, False
        )
    for n in bc.SIZES:
        q, qd = bc.initial_state(n)
        report(
            f"Cartesian chain N={n} (n={2 * n})",
            jl.System(bc.lagrangian, holonomic=bc.distance_constraints),
            q,
            qd,
            True,
        )


if __name__ == "__main__":
    main()
