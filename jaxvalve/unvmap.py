"""Reductions over a `jax.vmap` batch, for control flow that stays cheap under vmap.

Under vmap a `lax.cond` whose predicate differs between members becomes a select (both
branches run for every member), and a loop whose trip count differs runs with a select
on its whole carry at every trip.  `unvmap_any(pred)` and `unvmap_max(n)` are the identity
on unbatched values; under vmap they reduce over the batch to one unbatched value, so a
cond runs its branch once for the batch when any member needs it (each member then keeps
its own values by a ``jnp.where`` inside the branch) and a loop runs the largest trip
count with no select (extra trips of a member must be harmless: padding rows).  Equinox's
``unvmap_any`` and ``unvmap_max`` do the same.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

__all__ = ["unvmap_any", "unvmap_max"]


def _reduce(op, doc):
    def f(x):
        return x
    f.__doc__ = doc
    f = jax.custom_batching.custom_vmap(f)

    @f.def_vmap
    def rule(axis_size, in_batched, x):
        return (op(x, axis=0).astype(x.dtype) if in_batched[0] else x), False

    return f


unvmap_any = _reduce(jnp.any, "pred itself (bool array); under vmap, the OR over the batch.")
unvmap_max = _reduce(jnp.max, "n itself; under vmap, the maximum over the batch.")
