"""The Pallas kernel both ensemble kernels share (`jaxlag.experimental._ensemble.pallas`).

One program per block of ``block`` members (grid ``(⌈B/block⌉,)``, the last block padded by
repeating the last member) loads its members once, then for every save interval advances them
by the whole constant-step integration of that interval and stores their state: `run_kernel`.
What differs between the variants (the layout of the inputs and outputs, how a program starts
and advances an interval) is a `KernelPlan`.
"""

import abc
from collections.abc import Callable
from typing import Any

import equinox as eqx
import jax
import jax.numpy as jnp
from jax.experimental import pallas as pl
from jax.experimental.pallas import triton

__all__ = ["split_field", "KernelProblem", "KernelProgram", "KernelPlan", "run_kernel"]


def split_field(field):
    """``field``'s arrays as (per-member leaves, shared leaves) and a function rebuilding it."""
    per_member = (field.member_args, field.constant_mass)
    dynamic_members, static_members = eqx.partition(per_member, eqx.is_array)
    rest = eqx.tree_at(
        lambda f: (f.member_args, f.constant_mass), field, (None, None), is_leaf=lambda x: x is None
    )
    dynamic_shared, static_shared = eqx.partition(rest, eqx.is_array)

    def rebuild(members, shared):
        member_args, constant_mass = eqx.combine(members, static_members)
        base = eqx.combine(shared, static_shared)
        return eqx.tree_at(
            lambda f: (f.member_args, f.constant_mass),
            base,
            (member_args, constant_mass),
            is_leaf=lambda x: x is None,
        )

    return dynamic_members, dynamic_shared, rebuild


class KernelProblem(eqx.Module):
    """What both kernels start from: the batch cut into programs of ``block`` members (the last
    padded by repeating the last member), the field's per-member and shared arrays as flat leaf
    lists with their tree structures, and the function rebuilding the field from them."""

    batch: int = eqx.field(static=True)
    block: int = eqx.field(static=True)
    num_times: int = eqx.field(static=True)
    n: int = eqx.field(static=True)
    member_leaves: list[Any]
    shared_leaves: list[Any]
    member_def: Any = eqx.field(static=True)
    shared_def: Any = eqx.field(static=True)
    rebuild: Callable = eqx.field(static=True)

    @classmethod
    def of(cls, field, ts, y0, block: int) -> "KernelProblem":
        batch, num_times = ts.shape
        members, shared, rebuild = split_field(field)
        member_leaves, member_def = jax.tree.flatten(members)
        shared_leaves, shared_def = jax.tree.flatten(shared)
        return cls(
            batch, min(block, batch), num_times, y0[0].shape[1], member_leaves, shared_leaves,
            member_def, shared_def, rebuild,
        )  # fmt: skip

    @property
    def pad(self) -> int:
        return -self.batch % self.block

    @property
    def padded(self) -> int:
        return self.batch + self.pad

    def pad_members(self, x):
        if self.pad == 0:
            return x
        return jnp.concatenate([x, jnp.repeat(x[-1:], self.pad, axis=0)], axis=0)

    def field(self, member_vals, shared_vals):
        """The field of the given per-member and shared leaves."""
        return self.rebuild(
            jax.tree.unflatten(self.member_def, member_vals), jax.tree.unflatten(self.shared_def, shared_vals)
        )


class KernelProgram(eqx.Module):
    """What one Pallas program of a kernel variant does: ``start`` (``in_refs ↦ (carry,
    advance)``, ``advance(k, carry)`` integrating save interval ``k``), ``store`` the state of a
    save, and ``collect`` the kernel's outputs into the saves ``(q, q̇)`` each (T−1, B, n)."""

    @abc.abstractmethod
    def start(self, refs) -> tuple[Any, Callable]:
        raise NotImplementedError

    @abc.abstractmethod
    def store(self, out_refs, k, y) -> None:
        raise NotImplementedError

    @abc.abstractmethod
    def collect(self, outs):
        raise NotImplementedError


class KernelPlan(eqx.Module):
    """A kernel variant: its inputs and outputs with their block specs, and its program."""

    name: str = eqx.field(static=True)
    inputs: list[Any]
    in_specs: list[Any] = eqx.field(static=True)
    out_shape: list[Any] = eqx.field(static=True)
    out_specs: list[Any] = eqx.field(static=True)
    program: KernelProgram


def run_kernel(plan: KernelPlan, problem: KernelProblem, interpret: bool):
    """The kernel both variants share: one program per block of members loads them (``start``),
    then for every save interval advances them and stores the state."""
    num_out = len(plan.out_shape)

    def kernel(*refs):
        in_refs, out_refs = refs[:-num_out], refs[-num_out:]
        carry, advance = plan.program.start(in_refs)

        def one_interval(k, carry):
            carry = advance(k, carry)
            plan.program.store(out_refs, k, carry[0])
            return carry

        jax.lax.fori_loop(jnp.int32(0), jnp.int32(problem.num_times - 1), one_interval, carry)

    outs = pl.pallas_call(
        kernel,
        out_shape=plan.out_shape,
        grid=(problem.padded // problem.block,),
        in_specs=plan.in_specs,
        out_specs=plan.out_specs,
        interpret=interpret,
        name=plan.name,
        # Triton: it lowers float64 (Mosaic GPU, the default GPU lowering, loads no f64).
        compiler_params=triton.CompilerParams(num_warps=4),
    )(*plan.inputs)
    return plan.program.collect(outs)
