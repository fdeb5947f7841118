"""`quick_jit`: `jax.jit` for programs that compile long and run briefly.

On the CPU, XLA's newer fusion emitters (``xla_cpu_use_fusion_emitters``, on by default)
make faster loops but spend more time compiling them.  For a program run a handful of
times per optimisation (the smooth metrics with their gradient, the assembled tangent's
blocks, the residual's VJP in the adjoint; once per solve, its independent recheck, the
stall probe and the pair lists at its start) the compile time is what the user waits for:
with the older emitters these compile 1.3-1.7x faster and run within 10 % of the same
time (`benchmarks/quick_jit.py`).  The equilibrium solve, whose loop runs thousands of
steps, keeps the default.  Other backends ignore the
choice (the plain `jax.jit` is used there).  On the valve the outputs of the two
compilations differ by at most 6e-15 (`benchmarks/results/quick_jit.txt`).
"""
from __future__ import annotations

import functools

import jax

__all__ = ["quick_jit", "QUICK_CPU_OPTIONS"]

#: XLA compile options of `quick_jit` on the CPU backend.
QUICK_CPU_OPTIONS = {"xla_cpu_use_fusion_emitters": False}


class _QuickJit:
    """A jitted function compiled with `QUICK_CPU_OPTIONS` on the CPU, when called at the
    top level (with traced arguments, inside another jit or transformation, it is the
    plain `jax.jit`).  Attribute access (``lower``, ``_cache_size``, ...) goes to the
    top-level one."""

    def __init__(self, fun, jit_kw):
        self._plain = jax.jit(fun, **jit_kw)
        self._quick = jax.jit(fun, compiler_options=QUICK_CPU_OPTIONS, **jit_kw)
        functools.update_wrapper(self, fun)

    def _pick(self, args=()):
        # compile options apply to top-level programs only: inside another trace (traced
        # arguments) the plain jit is inlined into the caller's program
        traced = any(isinstance(v, jax.core.Tracer) for v in jax.tree_util.tree_leaves(args))
        return self._quick if jax.default_backend() == "cpu" and not traced else self._plain

    def __call__(self, *args, **kw):
        return self._pick((args, kw))(*args, **kw)

    def __getattr__(self, name):
        return getattr(self._pick(), name)


def quick_jit(fun=None, **jit_kw):
    """``jax.jit(fun, **jit_kw)``, compiled with `QUICK_CPU_OPTIONS` on the CPU.  Usable
    as a decorator, with or without keyword arguments."""
    if fun is None:
        return lambda f: _QuickJit(f, jit_kw)
    return _QuickJit(fun, jit_kw)
