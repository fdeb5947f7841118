"""Control flow that stays cheap, and exact, under `jax.vmap` (batch evaluation).

Under `jax.vmap` a `lax.cond` whose predicate differs between the members of the batch
becomes a `select`: both branches run for every member, every time.  A `lax.switch` on a
batched index runs all of its branches, and a loop with a batched trip count runs to the
largest one with a select on its whole carry at every trip.  Inside the solver loop this
was the contact pair list rebuilt for every member at every step and the contact energy
evaluated on all of its prefixes at every force evaluation: a plain `vmap` of the valve
closure took 32 ms a step for 3 members, against 0.7-0.9 ms a step for one valve alone
(h = 2 mm, StVK, on this 2-core machine).

The helpers here are the plain operation on unbatched values (a single solve is unchanged,
to the last bit).  Under vmap (`custom_vmap` rules) they keep each member's work what it is
in a sequential run:

* `cond_each(pred, true_fn, false_fn, *operands)`: ``lax.cond`` member by member.  The
  false branch (which should be cheap: an identity or a field update) runs vectorised.
  The true branch runs in one of two ways, chosen at trace time by `branches(policy)`:
  ``"members"`` (default) runs it, unbatched, only for the members whose pred is True (a
  loop over the batch, skipped when no member needs it: the least arithmetic, for a CPU);
  ``"select"`` runs it vectorised for the whole batch when any member needs it, and each
  member keeps its own branch's value (one array program whatever the batch size, for a
  GPU, where the member loop made a step's cost grow linearly with the batch).  Used for
  the pair-list rebuilds and FIRE's mass refresh.
* `each_active(pred, fn, *carry)`: ``fn`` run member by member, for the members whose
  pred is True, updating the batched carry in place (`solvers.base.iterate`: there fn is
  a member's whole solver loop).  Each member's operands are sliced out before they enter
  ``fn``, so ``fn`` is compiled as in an unbatched program and computes the same numbers
  as a single solve, bit for bit (a vectorised step does not: XLA orders some sums
  differently for batched arrays).
* `batch_max(n)`: the largest n of the batch, unbatched (loop trip counts over padded
  rows; the prefix length of a `lax.switch`).
* `batch_any(pred)`: the OR over the batch, unbatched.
* `batch_sum(n)`: the sum over the batch, unbatched (how many members are still running,
  for the straggler hand-off of `solvers.base.iterate(handoff=k)`).

Each use in the package is exact: a member's values do not depend on the batch it is in.
A longer prefix or more trips over padding give the same numbers (padding slots are masked
out), and `cond_each` gives each member its own branch.  The functions given to
`cond_each` may close over traced values: they are traced once to jaxprs whose constants
become explicit operands, so a batching rule that runs later meets no stale tracer.
"""
from __future__ import annotations

import contextlib

import jax
import jax.numpy as jnp

__all__ = ["batch_any", "batch_max", "batch_sum", "branches", "cond_each", "each_active"]

_POLICIES = ("members", "select")
_policy = ["members"]


@contextlib.contextmanager
def branches(policy: str):
    """Within this block, `cond_each` traced under vmap runs its true branch by ``policy``:
    "members" or "select" (module docstring).  Read when `cond_each` is called (traced),
    so two branches of one program may use different policies; a jitted caller must take
    the policy as a static argument, so that each policy gets its own trace."""
    if policy not in _POLICIES:
        raise ValueError(f"branches: policy must be one of {_POLICIES}; got {policy!r}")
    old, _policy[0] = _policy[0], policy
    try:
        yield
    finally:
        _policy[0] = old


def _batch_reduce(reduce, doc):
    """The identity, whose vmap rule reduces over the batch (unbatched result)."""
    def f(x):
        return x
    f.__doc__ = doc
    f = jax.custom_batching.custom_vmap(f)

    @f.def_vmap
    def rule(axis_size, in_batched, x):
        return (reduce(x, axis=0).astype(x.dtype) if in_batched[0] else x), False

    return f


batch_any = _batch_reduce(jnp.any, "pred (a bool array) itself; under vmap, the OR over the "
                                   "batch (unbatched).")
batch_max = _batch_reduce(jnp.max, "n itself; under vmap, the maximum over the batch "
                                   "(unbatched).")
batch_sum = _batch_reduce(jnp.sum, "n itself; under vmap, the sum over the batch (unbatched): "
                                   "with an int n = pred, the number of members for which "
                                   "pred is True.")


def _axes(batched):
    return jax.tree_util.tree_map(lambda b: 0 if b else None, batched)


def _vmap(fn, batched, ops, size):
    """fn over the batch (outputs all batched), also when no operand is batched."""
    if any(jax.tree_util.tree_leaves(batched)):
        return jax.vmap(fn, in_axes=tuple(_axes(b) for b in batched))(*ops)
    return jax.tree_util.tree_map(lambda a: jnp.broadcast_to(a, (size,) + a.shape), fn(*ops))


def _for_each_true(pred, body, acc):
    """``acc = body(i, acc)`` for each index i at which pred (B,) is True, in order: a loop
    over those members only (none: no trip, no copy; a straggler alone: one trip)."""
    which = jnp.nonzero(pred, size=pred.shape[0], fill_value=0)[0]
    return jax.lax.fori_loop(0, jnp.sum(pred, dtype=jnp.int32),
                             lambda k, a: body(which[k], a), acc)


def _closed(fn, operands):
    """fn as a function of (consts, *operands) with no closed-over traced values, and the
    consts: the values fn closes over become explicit inputs, so that a batching rule,
    which may run after the trace that made them, never meets a stale tracer."""
    jaxpr, shape = jax.make_jaxpr(fn, return_shape=True)(*operands)
    tree = jax.tree_util.tree_structure(shape)

    def run(consts, *ops):
        out = jax.core.eval_jaxpr(jaxpr.jaxpr, consts, *jax.tree_util.tree_leaves(ops))
        return jax.tree_util.tree_unflatten(tree, out)

    return run, list(jaxpr.consts)


def cond_each(pred, true_fn, false_fn, *operands):
    """``lax.cond(pred, true_fn, false_fn, *operands)``; under vmap each member takes its
    own branch, the true branch computed only for the members that need it (see the
    module docstring).  pred: a scalar bool per member; false_fn should be cheap."""
    policy = _policy[0]
    t_run, t_consts = _closed(true_fn, operands)
    f_run, f_consts = _closed(false_fn, operands)

    def t_fn(tc, fc, *ops):
        return t_run(tc, *ops)

    def f_fn(tc, fc, *ops):
        return f_run(fc, *ops)

    @jax.custom_batching.custom_vmap
    def f(pred, *ops):
        return jax.lax.cond(pred, t_fn, f_fn, *ops)

    @f.def_vmap
    def rule(axis_size, in_batched, pred, *ops):
        p_batched, o_batched = in_batched[0], in_batched[1:]
        if not p_batched:       # one decision for all: an ordinary cond over the batch
            out = jax.lax.cond(pred, lambda *o: _vmap(t_fn, o_batched, o, axis_size),
                               lambda *o: _vmap(f_fn, o_batched, o, axis_size), *ops)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        if policy == "select":
            def both(*o):
                t = _vmap(t_fn, o_batched, o, axis_size)
                f = _vmap(f_fn, o_batched, o, axis_size)
                return jax.tree_util.tree_map(
                    lambda a, b: jnp.where(pred.reshape((-1,) + (1,) * (a.ndim - 1)), a, b),
                    t, f)
            out = jax.lax.cond(jnp.any(pred), both,
                               lambda *o: _vmap(f_fn, o_batched, o, axis_size), *ops)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        acc = _vmap(f_fn, o_batched, ops, axis_size)

        def member(i, acc):
            # member i's operands are sliced out here and enter a branch (pred[i] is True)
            # as its inputs, so the branch is compiled as it is in an unbatched program
            ops_i = tuple(jax.tree_util.tree_map(lambda o, b: o[i] if b else o, op, b)
                          for op, b in zip(ops, o_batched))
            new = jax.lax.cond(pred[i], t_fn, lambda *o: jax.tree_util.tree_map(
                lambda a: a[i], acc), *ops_i)
            return jax.tree_util.tree_map(lambda a, v: a.at[i].set(v), acc, new)

        acc = _for_each_true(pred, member, acc)
        return acc, jax.tree_util.tree_map(lambda _: True, acc)

    return f(jnp.asarray(pred), t_consts, f_consts, *operands)


def each_active(pred, fn, *carry):
    """``fn(*carry) if pred else carry``, where fn returns carry's structure.  Under vmap,
    fn runs member by member, only for the members whose pred is True, updating the
    batched carry in place.  Each member's carry is sliced out before it enters fn, so fn
    is compiled as in an unbatched program and computes the same numbers as a single run,
    bit for bit."""
    run, consts = _closed(fn, carry)

    @jax.custom_batching.custom_vmap
    def f(pred, consts, *carry):
        return jax.lax.cond(pred, lambda c, *x: run(c, *x), lambda c, *x: x, consts, *carry)

    @f.def_vmap
    def rule(axis_size, in_batched, pred, consts, *carry):
        p_b, c_b, x_b = in_batched[0], in_batched[1], in_batched[2:]
        if not p_b:
            def all_members(c, *x):
                return _vmap(lambda c, *x: run(c, *x), (c_b,) + tuple(x_b), (c,) + x,
                             axis_size)
            out = jax.lax.cond(
                pred, all_members,
                lambda c, *x: tuple(_broadcast(v, b, axis_size) for v, b in zip(x, x_b)),
                consts, *carry)
            return out, jax.tree_util.tree_map(lambda _: True, out)
        carry = tuple(_broadcast(v, b, axis_size) for v, b in zip(carry, x_b))

        def member(i, carry):
            # slice, run, write back: the batched carry is only ever updated in place (a
            # cond over the whole carry made XLA copy it for every member)
            xi = jax.tree_util.tree_map(lambda a: a[i], carry)
            ci = jax.tree_util.tree_map(lambda a, b: a[i] if b else a, consts, c_b)
            new = run(ci, *xi)
            return jax.tree_util.tree_map(lambda a, v: a.at[i].set(v), carry, new)

        out = _for_each_true(pred, member, carry)
        return out, jax.tree_util.tree_map(lambda _: True, out)

    return f(jnp.asarray(pred), consts, *carry)


def _broadcast(tree, batched, size):
    """tree with every leaf batched (unbatched leaves repeated ``size`` times)."""
    return jax.tree_util.tree_map(
        lambda a, b: a if b else jnp.broadcast_to(a, (size,) + jnp.shape(a)), tree, batched)
