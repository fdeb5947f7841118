"""`jaxvalve.batching`: control flow under vmap, exact per member, by both branch policies."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve.batching import batch_any, batch_max, branches, cond_each


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
