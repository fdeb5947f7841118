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

Pairs: every (i, T) with |x_i - r_T| < d must be listed; a node closer than d to a
triangle's barycentre is closer than d to the triangle, so the point-triangle rows of a
pair list within d (`jaxvalve.contact.pairs`, rows [i, t0, t1, t2]) hold them; rows of one
body are skipped (the law acts between bodies).  Since d grows when the leaflets stretch,
the solve lists pairs within 1.25 d of its start (`jaxvalve.solvers.equilibrium`).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from ..errors import ParameterError
from .geometry import safe_norm

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

    def pair_forces(self, x, F_nc, delta, pairs, body, d):
        """Per-row contact forces (P, 3) in N of the point-triangle rows of ``pairs`` (a
        `jaxvalve.contact.pairs.PairList`); zero for padding, inactive rows and rows
        within one body (body (N,) ids); d: the vicinity threshold (mm)."""
        rows = pairs.pt
        i = rows[:, 0]
        xt = x[rows[:, 1:]]                                  # (P,3,3)
        rT = jnp.mean(xt, axis=1)
        nT = jnp.cross(xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0])
        nrm = safe_norm(nT)
        nT = nT / jnp.where(nrm > 0, nrm, 1.0)[:, None]
        near = safe_norm(x[i] - rT) < d
        Fi = F_nc[i]
        Fmag = safe_norm(Fi)
        dpi = jnp.sum((x[i] + delta * Fi - rT) * nT, axis=-1)
        pos_ok = Fmag > 0
        f_pos = jnp.where(pos_ok,
                          Fmag * jnp.exp(-self.k1 * dpi / jnp.where(pos_ok, Fmag, 1.0)), 0.0)
        f_neg = Fmag - self.k2 * dpi
        mag = jnp.where(dpi > 0, f_pos, f_neg)
        active = (pairs.pt_valid & near & (dpi < self.d_pi)
                  & (body[i] != body[rows[:, 1]]))
        return jnp.where(active[:, None], mag[:, None] * nT, 0.0)

    def force(self, x, F_nc, delta, pairs, body, triangles):
        """Contact forces (N,3) in N, eq. (2.2), summed over the triangles of other bodies.

        x (N,3) mm; F_nc (N,3) N non-contact (pressure + elastic) forces; delta mm/N;
        pairs: the point-triangle pair list; body (N,) ids; triangles (M, 3): the whole
        mesh, for the vicinity threshold."""
        f = self.pair_forces(x, F_nc, delta, pairs, body, vicinity_threshold(x, triangles))
        return jnp.zeros_like(x).at[pairs.pt[:, 0]].add(f)
