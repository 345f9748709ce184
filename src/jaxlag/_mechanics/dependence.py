"""Which inputs a function's output may depend on, read from its jaxpr (shapes only).

Used to find structure in a user's Lagrangian while tracing (a mass matrix that does not depend on
the state, a Lagrangian quadratic in the velocities) without evaluating anything. The analysis is
conservative — it never answers "independent" wrongly: an equation's outputs are taken to depend
on all of its inputs, except for calls whose body has the same inputs and outputs as the call
itself (``jit``-ted functions, custom derivatives, checkpoints), which are followed. Loops and
``cond`` are not followed (a loop carry can move a dependence from one output to another across
iterations), so they count as "depends on everything they take".
"""

import equinox as eqx
import jax
import jax.core
import jax.numpy as jnp
from jax.extend import core as jex_core

#: Primitives whose single sub-jaxpr maps the equation's inputs to its outputs one to one.
CALL_PRIMITIVES = frozenset(
    {
        "pjit",
        "jit",
        "closed_call",
        "core_call",
        "custom_jvp_call",
        "custom_vjp_call",
        "custom_vjp_call_jaxpr",
        "checkpoint",
        "remat",
        "remat2",
    }
)


def output_dependence(jaxpr, input_flags, const_flags) -> list[bool]:
    """For each output of ``jaxpr``, whether it may depend on an input or constant flagged True."""
    depends = dict(zip(jaxpr.constvars, const_flags))
    depends.update(zip(jaxpr.invars, input_flags))

    def flag_of(var):
        return False if isinstance(var, jex_core.Literal) else depends.get(var, False)

    for eqn in jaxpr.eqns:
        in_flags = [flag_of(v) for v in eqn.invars]
        out_flags = None
        if eqn.primitive.name in CALL_PRIMITIVES:
            bodies = list(jex_core.jaxprs_in_params(eqn.params))
            if (
                len(bodies) == 1
                and len(bodies[0].invars) == len(in_flags)
                and len(bodies[0].outvars) == len(eqn.outvars)
            ):
                body = bodies[0]
                out_flags = output_dependence(body, in_flags, [False] * len(body.constvars))
        if out_flags is None:
            out_flags = [any(in_flags)] * len(eqn.outvars)
        depends.update(zip(eqn.outvars, out_flags))
    return [flag_of(v) for v in jaxpr.outvars]


def may_depend(fn, inputs) -> tuple[list[bool], bool]:
    """Trace ``fn(*inputs)`` abstractly; return ``(per_input, on_closure)``.

    ``per_input[i]``: some output may depend on an array in the pytree ``inputs[i]`` (non-array
    leaves are static). ``on_closure``: some output may depend on a traced value that ``fn``
    closes over (a parameter of an enclosing ``jit``/``vmap``/``grad``).
    """
    dynamic, static = eqx.partition(tuple(inputs), eqx.is_array)
    leaves, treedef = jax.tree.flatten(dynamic)
    groups = [i for i, part in enumerate(dynamic) for _ in jax.tree.leaves(part)]
    abstract = [jax.ShapeDtypeStruct(jnp.shape(x), jnp.result_type(x)) for x in leaves]

    def flat_fn(*flat):
        return fn(*eqx.combine(jax.tree.unflatten(treedef, list(flat)), static))

    closed = jax.make_jaxpr(flat_fn)(*abstract)
    jaxpr = closed.jaxpr
    no_consts = [False] * len(jaxpr.constvars)
    per_input = []
    for g in range(len(inputs)):
        flags = [gi == g for gi in groups]
        per_input.append(any(output_dependence(jaxpr, flags, no_consts)))
    traced = [isinstance(c, jax.core.Tracer) for c in closed.consts]
    on_closure = any(traced) and any(output_dependence(jaxpr, [False] * len(groups), traced))
    return per_input, on_closure
