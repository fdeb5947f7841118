"""The paper's node-to-triangle contact force, eq. (2.2), reproduced as written.

Force-based (there is no energy; the law jumps at d^pi and at the vicinity bound, so it is
not differentiable and is meant for the damped fixed point of Algorithm 2.1).  For node i
and triangle T of another body, with barycentre r_T and unit normal n_T:

* vicinity threshold d = 1.1 / M * sum_T max_k |r_T - x_k| over ALL triangles (mm),
  recomputed from the current x (`vicinity_threshold`);
* if |x_i - r_T| < d: tentative position r~_i = x_i + delta F_i with F_i = F^p + F^e the
  non-contact force (N) and delta (mm/N) the fixed-point step; d^pi_{iT} = (r~_i - r_T).n_T;
* if d^pi_{iT} < d_pi:  F_{iT} = |F_i| exp(-k1 d^pi / |F_i|) n_T    (d^pi > 0),
                        F_{iT} = (|F_i| - k2 d^pi) n_T              (d^pi <= 0);
* F^c_i = sum_T F_{iT}.  Only node i is pushed (no reaction on T's vertices), as written.

|F_i| = 0 is guarded: the d^pi > 0 branch tends to 0 and is set to 0, the other gives
-k2 d^pi; no NaN.

Broad phase: the pairs must include every (i, T) with |x_i - r_T| < d.  `build_neighbours`
tests |x_i - r_T| < cutoff + R_T, so cutoff >= d (+ skin for reuse) suffices; since d grows
when the leaflets stretch, build with e.g. ``cutoff = 1.25 * vicinity_threshold(x, tri) +
skin`` (for the paper's ~1 mm triangles d is ~0.7 mm; a few mm in all for coarse meshes).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from ..errors import ParameterError
from .geometry import safe_norm
from .neighbours import NeighbourList

__all__ = ["PaperContact", "vicinity_threshold"]


def vicinity_threshold(x, triangles):
    """d = 1.1 * mean_T max_k |r_T - x_k| (mm), over all triangles, from positions x."""
    xt = x[triangles]
    rT = jnp.mean(xt, axis=1)
    return 1.1 * jnp.mean(jnp.max(safe_norm(xt - rT[:, None]), axis=1))


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["k1", "k2", "d_pi"], meta_fields=[])
@dataclasses.dataclass(frozen=True)
class PaperContact:
    """Eq. (2.2). k1 = 0.8 N/m = 8e-4 N/mm, k2 = 20 N/m = 0.02 N/mm, d_pi = 0.7 mm."""

    k1: float | jax.Array = 8e-4
    k2: float | jax.Array = 0.02
    d_pi: float | jax.Array = 0.7

    def validate(self) -> "PaperContact":
        """Host-side check; raises `ParameterError` naming the parameter and its range."""
        for name, unit in (("k1", "N/mm"), ("k2", "N/mm"), ("d_pi", "mm")):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v <= 0:
                raise ParameterError(f"PaperContact.{name} must be > 0 and finite; "
                                     f"got {v} {unit}")
        return self

    def pair_forces(self, x, F_nc, delta, triangles, nbrs: NeighbourList):
        """Per-row contact forces (capacity, 3) in N (zero for padding/inactive rows)."""
        n, m = x.shape[0], triangles.shape[0]
        i = jnp.clip(nbrs.pairs[:, 0], 0, n - 1)
        tri = triangles[jnp.clip(nbrs.pairs[:, 1], 0, m - 1)]
        xt = x[tri]                                          # (P,3,3)
        rT = jnp.mean(xt, axis=1)
        nT = jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
        nrm = safe_norm(nT)
        nT = nT / jnp.where(nrm > 0, nrm, 1.0)[:, None]
        d = vicinity_threshold(x, triangles)
        near = safe_norm(x[i] - rT) < d
        Fi = F_nc[i]
        Fmag = safe_norm(Fi)
        dpi = jnp.sum((x[i] + delta * Fi - rT) * nT, axis=-1)
        pos_ok = Fmag > 0
        f_pos = jnp.where(pos_ok,
                          Fmag * jnp.exp(-self.k1 * dpi / jnp.where(pos_ok, Fmag, 1.0)), 0.0)
        f_neg = Fmag - self.k2 * dpi
        mag = jnp.where(dpi > 0, f_pos, f_neg)
        active = nbrs.valid & near & (dpi < self.d_pi)
        return jnp.where(active[:, None], mag[:, None] * nT, 0.0)

    def force(self, x, F_nc, delta, triangles, nbrs: NeighbourList):
        """Contact forces (N,3) in N, eq. (2.2), summed over the triangles of other bodies.

        x (N,3) mm; F_nc (N,3) N non-contact (pressure + elastic) forces; delta mm/N.
        """
        f = self.pair_forces(x, F_nc, delta, triangles, nbrs)
        i = jnp.clip(nbrs.pairs[:, 0], 0, x.shape[0] - 1)
        return jnp.zeros_like(x).at[i].add(f)
