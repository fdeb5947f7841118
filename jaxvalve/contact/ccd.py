"""Continuous collision detection: the largest step that keeps every pair apart.

Additive CCD (Li, Kaufman and Jiang 2021, "Codimensional incremental potential contact",
Algorithm 1), vectorised over pairs in NumPy.  Along the straight move x + t dx,
t in [0, 1], each pair advances by steps that its distance proves safe: with l_p an upper
bound on the rate at which the pair's distance can shrink (the largest relative
displacement of its point or first edge plus the largest of its triangle or second edge,
after removing the pair's mean displacement), the distance stays positive for a further
t_l = (1 - s) d / l_p.  A pair stops at the first t where its distance has fallen below
s d_0 (s = 0.1 by default: at most 90 % of the starting gap may close) or when t reaches 1.
Every t returned is conservative: no distance reaches zero on [0, t], whatever the motion
between the samples, because d(t) >= d(t_k) - l_p (t - t_k) > 0 on each advance.
"""
from __future__ import annotations

import numpy as np

from ..errors import ParameterError
from .ipc_distance import point_triangle_distance2_np, segment_distance2_np

__all__ = ["additive_ccd", "max_step"]


def additive_ccd(x4, dx4, kind, s=0.1, max_iter=200, cap=1.0, smallest=False):
    """Largest safe fraction t in [0, cap] (K,) of the moves dx4 (K, 4, 3) for pairs at x4
    (K, 4, 3) mm: rows [p, t0, t1, t2] for kind "pt", [a0, a1, b0, b1] for kind "ee".
    A pair still short of its bound after max_iter advances returns the safe t reached.

    smallest: only the smallest t is wanted (`max_step`): cap falls to the smallest t of
    any pair that has stopped, and a pair is no longer advanced once its safe t reaches
    cap (its own t can only be larger).  The minimum over the pairs is the same; the
    other entries are then min(t, the final cap)."""
    cap = float(cap)
    if not 0.0 <= cap <= 1.0:
        raise ParameterError(f"cap must be a step fraction in [0, 1]; got {cap!r}")
    x4 = np.asarray(x4, float)
    dx4 = np.asarray(dx4, float)
    K = x4.shape[0]
    if K == 0:
        return np.ones(0)
    dist2 = point_triangle_distance2_np if kind == "pt" else segment_distance2_np
    split = 1 if kind == "pt" else 2
    rel = dx4 - dx4.mean(axis=1, keepdims=True)
    speed = np.linalg.norm(rel, axis=2)
    lp = speed[:, :split].max(axis=1) + speed[:, split:].max(axis=1)
    d0 = np.sqrt(dist2(*(x4[:, k] for k in range(4))))
    t = np.zeros(K)
    out = np.full(K, cap)
    active = lp > 0
    t_l = np.where(active, (1.0 - s) * d0 / np.where(active, lp, 1.0), 0.0)
    first = np.ones(K, bool)
    for _ in range(max_iter):
        idx = np.flatnonzero(active)
        if idx.size == 0:
            break
        tt = t[idx] + t_l[idx]
        xs = x4[idx] + tt[:, None, None] * dx4[idx]
        d = np.sqrt(dist2(*(xs[:, k] for k in range(4))))
        # the advance to tt is safe (t_l <= d(t) / l_p); stop where the gap fell below s d0
        hit = d < s * d0[idx]
        done_hit = idx[hit & ~first[idx]]
        out[done_hit] = t[done_hit]
        # first advance that already falls below s d0: take it (t stays 0 otherwise)
        first_hit = idx[hit & first[idx]]
        out[first_hit] = tt[hit & first[idx]]
        if smallest and idx[hit].size:
            cap = min(cap, float(out[idx[hit]].min()))
        go = idx[~hit]
        t[go] = tt[~hit]
        over = go[t[go] >= cap]
        out[over] = cap
        first[idx] = False
        active[idx[hit]] = False
        active[over] = False
        if smallest:          # pairs whose safe t already reached the smallest stop
            active &= t < cap
        still = go[t[go] < cap]
        t_l[still] = 0.9 * d[~hit][t[go] < cap] / lp[still]
    else:
        left = np.flatnonzero(active)
        out[left] = t[left]
    return np.minimum(out, cap)


def max_step(x, dx, pairs, s=0.1, smallest=True):
    """Largest t in [0, 1] such that no pair of ``pairs`` (`ipc_pairs.BarrierPairs`) meets
    on the move x + t dx (x, dx (N, 3) mm).  The caller guarantees that the pairs hold
    every pair that can come within reach of each other on the move (a list built with
    cutoff > 2 max |dx|).  smallest: `additive_ccd`'s, for each kind of pair (False:
    every pair followed to its own bound; the same t, `benchmarks/ccd_smallest.py`)."""
    x = np.asarray(x, float)
    dx = np.asarray(dx, float)
    t = 1.0
    for kind, rows in (("pt", pairs.pt), ("ee", pairs.ee)):
        if len(rows):
            t = min(t, float(np.min(additive_ccd(x[rows], dx[rows], kind, s, cap=t,
                                                 smallest=smallest))))
    return t
