"""`jaxvalve.vmap_control`: control flow under vmap, exact per member, by both branch policies."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.vmap_control import batch_any, batch_max, branches, cond_each


def _true(x, k):
    return jnp.sin(x) * k + 1.0, k + 1


def _false(x, k):
    return x, k


def _per_member(pred, x, k):
    return jax.lax.cond(pred, _true, _false, x, k)


@pytest.mark.parametrize("policy", ["members", "select"])
def test_cond_each_takes_each_members_own_branch(policy):
    pred = jnp.array([True, False, True, False])
    x = jnp.linspace(0.1, 0.9, 12).reshape(4, 3)
    k = jnp.arange(4)
    f = jax.vmap(lambda p, x, k: cond_each(p, _true, _false, x, k))
    with branches(policy):
        got = jax.jit(f)(pred, x, k)
        none = jax.jit(f)(jnp.zeros(4, bool), x, k)
        shape = jax.make_jaxpr(f)(pred, x, k)
    want = jax.vmap(_per_member)(pred, x, k)
    for g, w in zip(got, want):
        np.testing.assert_array_equal(g, w)
    np.testing.assert_array_equal(none[0], x)          # no member due: nothing changes
    np.testing.assert_array_equal(none[1], k)
    # "members" loops over the members that are due; "select" is one array program
    assert ("while[" in str(shape)) == (policy == "members")


def test_unbatched_calls_are_the_plain_operations():
    x = jnp.array([0.3, 0.7])
    np.testing.assert_array_equal(cond_each(True, _true, _false, x, 2)[0], _true(x, 2)[0])
    np.testing.assert_array_equal(cond_each(False, _true, _false, x, 2)[0], x)
    assert batch_max(jnp.int32(3)) == 3 and bool(batch_any(jnp.bool_(False))) is False
    # under vmap: the reduction over the batch, unbatched
    n = jax.vmap(lambda n: batch_max(n) + 0 * n)(jnp.array([2, 7, 5]))
    np.testing.assert_array_equal(n, [7, 7, 7])
    a = jax.vmap(lambda p: batch_any(p) | p)(jnp.array([False, True, False]))
    np.testing.assert_array_equal(a, [True, True, True])


def test_unknown_policy_is_rejected():
    with pytest.raises(ValueError, match="policy must be one of"):
        with branches("gpu"):
            pass


# ------------------------------------------------------------------ straggler hand-off
@jax.custom_batching.custom_vmap
def _vectorised(x):
    """0 in an unbatched program; 1 where the operation runs vectorised over a batch."""
    return jnp.zeros_like(x)


@_vectorised.def_vmap
def _vectorised_rule(axis_size, in_batched, x):
    return jnp.ones_like(x), in_batched[0]


class _Contract:
    """A toy solver: y <- (1 - k) y until |y| < 1e-6 (k per member, in args); its state
    counts the steps that ran vectorised."""

    max_steps = 1000

    def init(self, system, y, args):
        return {"F": -args["k"] * y, "vec": jnp.zeros((), jnp.int32)}

    def step(self, system, y, args, state):
        y = y - args["k"] * y
        return y, {"F": -args["k"] * y, "vec": state["vec"] + _vectorised(state["vec"])}

    def terminate(self, system, y, args, state):
        done = jnp.linalg.norm(y) < 1e-6
        return done, jnp.where(done, 0, 1)


def _contract(y0, k, handoff):
    from types import SimpleNamespace

    from jaxvalve.solvers.base import iterate
    system = SimpleNamespace(update=lambda y, args: args,
                             scale=lambda y, args: jnp.asarray(1.0, y.dtype))
    args = {"k": k, "nbrs": jnp.zeros(()), "f0": jnp.asarray(-1.0)}
    y, _, state, result, n = iterate(_Contract(), system, y0, args, handoff=handoff,
                                     beacon=False)     # vectorised steps: as jaxvalve.batch
    return y, n, result, state["vec"]


@pytest.mark.parametrize("handoff", [0, 1, 2, 3])
def test_vectorised_loop_hands_the_last_members_over_to_the_member_loop(handoff):
    """iterate(handoff=h) under vmap: the steps run vectorised while more than h members
    are running, then member by member (a straggler's last steps are its own); every member
    ends exactly as when solved alone."""
    from jaxvalve import progress
    y0 = jnp.array([[1.0, 2.0], [0.5, -1.0], [3.0, 0.1]])
    k = jnp.array([0.5, 0.2, 0.05])                   # 22, 66 and 290 steps
    before = progress.latest()
    y, n, result, vec = jax.jit(jax.vmap(lambda y, k: _contract(y, k, handoff)))(y0, k)
    jax.effects_barrier()
    after = progress.latest()
    # each member handed over to its own loop reports its end (`progress.member_done`),
    # and its steps there (a beacon every BEACON_EVERY = 100 steps: the slowest member,
    # 290 steps, passes steps 100 and 200 in its own loop whenever there is a hand-off);
    # the vectorised steps report nothing
    assert after["members"] - before["members"] == min(handoff, 3)
    assert after["serial"] - before["serial"] == (2 if handoff else 0)
    for i in range(3):
        yi, ni, ri, vi = jax.jit(lambda y, k: _contract(y, k, 0))(y0[i], k[i])
        np.testing.assert_array_equal(y[i], yi)
        assert int(n[i]) == int(ni) and int(result[i]) == int(ri) == 0 and int(vi) == 0
    steps = np.asarray(n)
    assert len(set(steps.tolist())) == 3 and steps.max() > 250
    # trips with more than `handoff` members running were vectorised, the rest were not
    running = [int(np.sum(steps > t)) for t in range(int(steps.max()))]
    want = [sum(1 for t in range(s) if running[t] > handoff) for s in steps]
    if handoff == 0:
        want = list(steps)                           # the plain vectorised loop
    np.testing.assert_array_equal(vec, want)
