"""The one sparse assembly (`tangent.BlockAssembler`): blocks summed over node tuples into
the free dofs, checked against a dense sum written out independently."""
import numpy as np
import pytest

from jaxvalve.solvers.tangent import BlockAssembler


def _dense(blocks, nodes, free):
    """The dense (3N, 3N) sum of the blocks, restricted to the free dofs."""
    N = free.size
    K = np.zeros((3 * N, 3 * N))
    for H, nd in zip(blocks, nodes):
        d = (3 * nd[:, None] + np.arange(3)).ravel()
        K[np.ix_(d, d)] += H
    f = np.repeat(free, 3)
    return K[np.ix_(f, f)]


@pytest.fixture
def case():
    rng = np.random.default_rng(3)
    N = 9
    free = np.ones(N, bool)
    free[[0, 4]] = False
    tri = np.array([rng.choice(N, 3, replace=False) for _ in range(12)])
    quad = np.array([rng.choice(N, 4, replace=False) for _ in range(5)])
    tri = np.concatenate([tri, tri[:2]])              # repeated tuples must add up
    return free, tri, rng.normal(size=(len(tri), 9, 9)), quad, rng.normal(size=(5, 12, 12))


def test_coo_and_the_fixed_pattern_give_the_dense_sum(case):
    free, tri, Ht, quad, Hq = case
    asm = BlockAssembler(free)
    assert asm.nf == 3 * int(free.sum())
    want = _dense(list(Ht) + list(Hq), list(tri) + list(quad), free)
    np.testing.assert_allclose(asm.coo(Ht, tri).toarray() + asm.coo(Hq, quad).toarray(),
                               want, atol=1e-12)
    pat = asm.pattern([tri, quad])
    K = pat.matrix([Ht, Hq])
    np.testing.assert_allclose(K.toarray(), want, atol=1e-12)
    assert pat.nnz == np.count_nonzero(want)
    # the same pattern serves new values (the solver's Newton steps)
    np.testing.assert_allclose(pat.matrix([2 * Ht, -Hq]).toarray(),
                               _dense(list(2 * Ht) + list(-Hq), list(tri) + list(quad), free),
                               atol=1e-12)
