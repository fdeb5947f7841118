"""The broad phase (`jaxvalve.geometry.broad_phase.ball_pairs`): every pair of balls within
the gap is listed, against brute force, and one ballooned ball does not make every pair a
candidate."""
import numpy as np
import pytest

from jaxvalve.errors import ParameterError
from jaxvalve.geometry.broad_phase import ball_pairs


def _balls(rng, n, big=()):
    """n balls on a wavy sheet 20 mm across, radii 0.4-1.2 mm, some made ``big``."""
    uv = rng.uniform(0, 20, (n, 2))
    c = np.column_stack([uv, np.sin(uv[:, 0] / 3.0)])
    r = rng.uniform(0.4, 1.2, n)
    r[list(big)] = [15.0, 6.0, 3.0][:len(big)]
    return c, r


def _brute(ca, ra, cb, rb, gap, self_pairs):
    d = np.linalg.norm(ca[:, None] - cb[None], axis=2)
    hit = d <= gap + ra[:, None] + rb[None]
    if self_pairs:
        hit &= np.triu(np.ones_like(hit), 1).astype(bool)
    return {tuple(p) for p in np.argwhere(hit)}


@pytest.mark.parametrize("big", [(), (3,), (3, 50, 77)])
@pytest.mark.parametrize("gap", [0.0, 0.7])
def test_every_pair_within_the_gap_is_listed(big, gap):
    rng = np.random.default_rng(len(big) + int(10 * gap))
    c, r = _balls(rng, 300, big)
    got = ball_pairs(c, r, gap=gap)
    assert np.all(got[:, 0] < got[:, 1])
    assert len({tuple(p) for p in got}) == len(got)          # each pair once
    assert _brute(c, r, c, r, gap, True) <= {tuple(p) for p in got}
    # two sets: points (radius 0) against balls, as the contact's nodes and triangles
    p = rng.uniform(0, 20, (200, 3))
    got = ball_pairs(p, 0.0, c, r, gap)
    assert _brute(p, np.zeros(200), c, r, gap, False) <= {tuple(q) for q in got}


def test_one_ballooned_ball_widens_only_its_own_queries():
    """A single 15 mm ball among 2000 of about 1 mm: one query radius for all (gap + 2
    max r) would list nearly every pair; by size class the candidates grow by about the
    big ball's own neighbours."""
    rng = np.random.default_rng(7)
    c, r = _balls(rng, 2000)
    base = len(ball_pairs(c, r, gap=0.2))
    r[11] = 15.0
    grown = len(ball_pairs(c, r, gap=0.2))
    one_radius = len(_brute(c, np.full(2000, 15.0), c, np.full(2000, 15.0), 0.2, True))
    assert grown <= base + 2000
    assert one_radius > 10 * grown


@pytest.mark.parametrize("bad", ["nan", "negative", "gap"])
def test_bad_input_is_refused(bad):
    c, r = _balls(np.random.default_rng(0), 10)
    gap = 0.1
    if bad == "nan":
        c[2, 1] = np.nan
    elif bad == "negative":
        r[4] = -1.0
    else:
        gap = -0.1
    with pytest.raises(ParameterError, match="finite"):
        ball_pairs(c, r, gap=gap)
