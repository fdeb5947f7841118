"""Smooth (C1) penalty contact energy between membrane bodies: the differentiable default.

Energy (N mm), with d_{i,B} = unsigned distance (mm) from node i to the surface of body B
(the minimum over B's triangles in the neighbour list) and a_i the lumped reference area of
node i (mm^2, sum of A_T / 3 over its triangles):

    E = sum_i sum_{B != body(i)} (1/2) a_i phi(d_{i,B}),    phi(d) = (k/2) (g0 - d)_+^2.

* phi and phi' vanish at d = g0: no jump in value or force at the activation distance; phi
  is C1 (phi'' jumps by k at g0).
* Mesh independence: a node is pushed by the *nearest* point of each other body, once per
  body, so a flat sheet at distance d < g0 from a flat sheet feels d E / d d = a_i k (g0 -
  d) whatever the triangle sizes (summing over all triangles in range would count a node
  above a shared edge twice, and ~ (g0 / h)^2 triangles on a fine mesh).  The minimum of
  point-triangle distances of one surface is C1 across shared edges and vertices (the
  minimisers coincide there); it has kinks only on the surface's medial axis, e.g. a node
  equidistant from two distinct folds of the same leaflet.
* The node-to-surface term is evaluated in both directions (nodes of A against the surface
  of B and nodes of B against A) with weight 1/2, so that the pressure between two sheets
  is p = k (g0 - d) (MPa) on each, symmetric in A and B; a lone node over a sheet feels
  half of it.  Forces are -grad E: they sum to zero (translation invariance) and have zero
  net torque (rotation invariance); the reaction acts on the triangle's vertices with the
  barycentric weights of the closest point.

Defaults: g0 = 0.2 mm (well below the coaptation threshold g_c = 0.5 mm, so touching
leaflets are counted as coapting: their gap is <= g0 < g_c), k = 1 MPa/mm.  Two sheets
pressed at the diastolic 80 mmHg = 0.010666 MPa settle at g0 - P/k = 0.189 mm: the
penetration into the layer is 5 % of g0, and sheets reach d = 0 (where an unsigned-distance
penalty loses its sense of side) only above P = k g0 = 0.2 MPa = 1500 mmHg.  The nodal
contact stiffness k a_i ~ 1 N/mm for ~1 mm^2 nodes is of the order of the membrane stiffness
E H ~ 0.3 N/mm, which keeps the equilibrium solve well conditioned.
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp

from ..errors import ParameterError
from .geometry import point_triangle_distance
from .neighbours import NeighbourList

__all__ = ["SmoothContact", "pair_distances", "node_areas"]


def node_areas(x_ref, triangles):
    """Lumped node areas (N,) in mm^2: sum of A_T / 3 over the triangles of each node."""
    xt = x_ref[triangles]
    e1, e2 = xt[:, 1] - xt[:, 0], xt[:, 2] - xt[:, 0]
    if x_ref.shape[1] == 2:
        area = 0.5 * jnp.abs(e1[:, 0] * e2[:, 1] - e1[:, 1] * e2[:, 0])
    else:
        area = 0.5 * jnp.linalg.norm(jnp.cross(e1, e2), axis=-1)
    return jnp.zeros(x_ref.shape[0], x_ref.dtype).at[triangles].add(area[:, None] / 3.0)


def pair_distances(x, triangles, nbrs: NeighbourList, signed: bool = False):
    """Node-triangle distances (capacity,) in mm for the rows of `nbrs`; padding rows get
    +inf.  With ``signed``, also the side (capacity,): -1 where the node lies over the
    triangle's face on its -n side (n = (b - a) x (c - a)), else +1."""
    n, m = x.shape[0], triangles.shape[0]
    valid = nbrs.valid
    i = jnp.clip(nbrs.pairs[:, 0], 0, n - 1)
    t = triangles[jnp.clip(nbrs.pairs[:, 1], 0, m - 1)]
    p, a, b, c = x[i], x[t[:, 0]], x[t[:, 1]], x[t[:, 2]]
    d, q, bary = jax.vmap(point_triangle_distance)(p, a, b, c)
    d = jnp.where(valid, d, jnp.inf)
    if not signed:
        return d
    # negative only for a node over the face (closest point inside it) on its -n side:
    # a node beside the sheet, beyond an edge, is not a crossing
    nrm = jnp.cross(b - a, c - a)
    over = jnp.all(bary > 0, axis=-1)
    side = jnp.where(over & (jnp.sum((p - q) * nrm, axis=-1) < 0), -1.0, 1.0)
    return d, side


@functools.partial(jax.tree_util.register_dataclass,
                   data_fields=["stiffness", "gap"], meta_fields=["one_sided"])
@dataclasses.dataclass(frozen=True)
class SmoothContact:
    """C1 penalty contact: pressure k (g0 - d)_+ between sheets (see module docstring).

    stiffness: k, contact pressure per unit penetration into the layer (MPa/mm).
    gap: g0, activation distance (mm); build the neighbour list with cutoff >= gap + skin.
    Both are traced (differentiable) fields.
    one_sided: (static) measure the gap as a signed distance s = +-d, positive on the +n
    side of the nearest triangle of the other body, and penalise (k/2)(g0 - s)_+^2.  A node
    that crossed the other sheet is then pushed back, never further through.  Use it when
    the bodies face each other with their +n sides, as valve leaflets do (their normals
    point from the aortic to the ventricular side, and their ventricular sides coapt).
    """

    stiffness: float | jax.Array = 1.0
    gap: float | jax.Array = 0.2
    one_sided: bool = False

    def validate(self) -> "SmoothContact":
        """Host-side check; raises `ParameterError` naming the parameter and its range."""
        for name, hi in (("stiffness", math.inf), ("gap", 0.5)):
            v = float(getattr(self, name))
            if not math.isfinite(v) or v <= 0 or v >= hi:
                rng = "> 0 and finite" if hi == math.inf else f"in (0, {hi}) mm"
                unit = "MPa/mm" if name == "stiffness" else "mm"
                raise ParameterError(f"SmoothContact.{name} must be {rng}; got {v} {unit}"
                                     + (" (g0 must stay below the coaptation threshold "
                                        "g_c = 0.5 mm)" if name == "gap" else ""))
        return self

    def potential(self, d):
        """phi(d) = (k/2) (g0 - d)_+^2 in MPa mm = N/mm (energy per unit area)."""
        s = jnp.maximum(self.gap - d, 0.0)
        return 0.5 * self.stiffness * s * s

    def energy(self, x, triangles, nbrs: NeighbourList, node_area):
        """Contact energy (N mm) for positions x (N,3) mm, node_area (N,) mm^2."""
        cap = nbrs.capacity
        seg = dict(segment_ids=nbrs.group, num_segments=cap, indices_are_sorted=True)
        if self.one_sided:
            d, side = pair_distances(x, triangles, nbrs, signed=True)
            dmin = jax.ops.segment_min(d, **seg)
            # the side of the nearest triangle; on a tie (a shared edge) the + side wins
            near = nbrs.valid & (d <= dmin[nbrs.group])
            side = jax.ops.segment_max(jnp.where(near, side, -1.0), **seg)
            dmin = jnp.where(jnp.isfinite(dmin), side * dmin, self.gap)
        else:
            d = pair_distances(x, triangles, nbrs)
            dmin = jax.ops.segment_min(d, **seg)
        dmin = jnp.minimum(dmin, self.gap)           # empty / padding groups -> no energy
        node = jax.ops.segment_max(jnp.where(nbrs.valid, nbrs.pairs[:, 0], 0), **seg)
        area = node_area[jnp.clip(node, 0, x.shape[0] - 1)]
        return 0.5 * jnp.sum(area * self.potential(dmin))

    def forces(self, x, triangles, nbrs: NeighbourList, node_area):
        """Contact forces (N,3) in N: -grad energy."""
        return -jax.grad(self.energy)(x, triangles, nbrs, node_area)
