"""Template parameters -> reference mesh, differentiably, with the mesh topology held fixed.

The mesher (`leaflet_mesh.mesh_leaflet`) is not differentiable: a new (r, a, b, alpha)
gives new nodes and new triangles.  For gradients, `TemplateMap` keeps one mesh's
triangles and moves its nodes:

* each boundary node keeps its edge (A-B, the arc B-C, C-D, A-E or E-D) and its fraction
  of that edge's length, so the corners stay corners and the nodes stay evenly spaced;
* the interior nodes follow by the harmonic extension of the boundary displacement
  (cotangent Laplacian of the base mesh): a fixed linear map, computed once as a dense
  (interior x boundary) matrix.

At the base parameters the map returns the mesher's nodes exactly.  Everything below
`points` and `sutured_t` is written in jax.numpy and is differentiable in (r, a, b, alpha).
When the template moves far, triangles distort: `quality` reports the minimum angle and
`needs_remesh` says when to call the mesher again (outside the gradient).
"""
from __future__ import annotations

import dataclasses
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import scipy.sparse.linalg as spla

from ..errors import MeshError, ParameterError
from .leaflet_mesh import LeafletMesh, _edge_counts, mesh_quality
from .mesh import signed_areas_np
from ..valve.placement import cot_laplacian
from .template import Template, corners

__all__ = ["TemplateMap", "template_map", "EDGES"]

#: Boundary edges, in the order of their ids: sutured A-B, arc B-C, C-D; free A-E, E-D.
EDGES = ("AB", "BC", "CD", "AE", "ED")


@dataclasses.dataclass(frozen=True)
class TemplateMap:
    """Fixed-topology map theta = (r, a, b, alpha) -> nodes (N, 2) mm of a leaflet mesh.

    base: the `LeafletMesh` it was built from.  boundary (K,): node indices; edge (K,):
    edge id (`EDGES`) of each; frac (K,): fraction of that edge's length from its first
    corner.  interior (N - K,): the other nodes; extension (N - K, K): harmonic extension
    matrix of the base mesh (interior displacement = extension @ boundary displacement).
    """

    base: LeafletMesh
    boundary: np.ndarray
    edge: np.ndarray
    frac: np.ndarray
    interior: np.ndarray
    extension: np.ndarray

    @property
    def triangles(self):
        return self.base.triangles

    def boundary_points(self, r, a, b, alpha=160.0):
        """Boundary nodes (K, 2) mm for the template (r, a, b, alpha); differentiable."""
        _, A, B, C, D, E = corners(r, a, b, alpha, jnp)
        beta = alpha * (math.pi / 360.0)
        f = jnp.asarray(self.frac)[:, None]
        phi = -beta + 2.0 * beta * f[:, 0]
        arc = jnp.stack([r * jnp.sin(phi), -r * jnp.cos(phi)], axis=1)
        lines = [A + f * (B - A), arc, C + f * (D - C), A + f * (E - A), E + f * (D - E)]
        out = lines[4]
        for k in range(3, -1, -1):
            out = jnp.where((self.edge == k)[:, None], lines[k], out)
        return out

    def points(self, r, a, b, alpha=160.0):
        """All nodes (N, 2) mm: the boundary by `boundary_points`, the interior by the
        harmonic extension of the boundary displacement from the base mesh."""
        p0 = jnp.asarray(self.base.points)
        pb = self.boundary_points(r, a, b, alpha)
        du = pb - p0[self.boundary]
        pi = p0[self.interior] + jnp.asarray(self.extension) @ du
        return jnp.zeros_like(p0).at[self.boundary].set(pb).at[self.interior].set(pi)

    def sutured_t(self, r, a, alpha=160.0):
        """Arc-length fraction (n_s,) of A-B-C-D at each sutured node (base order)."""
        beta = alpha * (math.pi / 360.0)
        L_arc = 2.0 * beta * r
        L = 2.0 * a + L_arc
        e, f = self.edge[self.base.sutured], jnp.asarray(self.frac[self.base.sutured])
        u = jnp.where(e == 0, f * a, jnp.where(e == 1, a + f * L_arc, a + L_arc + f * a))
        return u / L

    @functools.cached_property
    def _points_host(self):
        """`points` compiled once for the host checks below (eager jax.numpy would
        compile each of its operations)."""
        return jax.jit(self.points)

    def quality(self, r, a, b, alpha=160.0) -> dict:
        """`mesh_quality` of the mapped mesh (host-side, concrete parameters)."""
        p = np.asarray(self._points_host(float(r), float(a), float(b), float(alpha)))
        return mesh_quality(p, self.base.triangles)

    def needs_remesh(self, r, a, b, alpha=160.0, min_angle=15.0) -> bool:
        """True when the mapped mesh has an angle below ``min_angle`` degrees or an
        inverted triangle: time to mesh the new template afresh (outside the gradient)."""
        p = np.asarray(self._points_host(float(r), float(a), float(b), float(alpha)))
        t = self.base.triangles
        if np.min(signed_areas_np(p, t)) <= 0:
            return True
        return mesh_quality(p, t)["min_angle"] < min_angle


def _boundary_layout(tpl: Template, h: float):
    """(edge id, fraction) of each boundary node, in `leaflet_mesh._boundary` order."""
    na, nc, _, nb, _ = _edge_counts(tpl, h)
    edge = [0] * na + [1] * nc + [2] * (na + 1)
    frac = [j / na for j in range(na)] + [j / nc for j in range(nc)] + \
           [j / na for j in range(na + 1)]
    # free edge from D back to A without the corners: E-D from D to E, then A-E from E to A
    edge += [4] * nb + [3] * (nb - 1)
    frac += [j / nb for j in range(nb - 1, -1, -1)] + [j / nb for j in range(nb - 1, 0, -1)]
    return np.asarray(edge, np.int32), np.asarray(frac, float)


def template_map(mesh: LeafletMesh) -> TemplateMap:
    """Build the `TemplateMap` of a mesh made by `mesh_leaflet` (raises `MeshError` if its
    boundary does not follow the template's edges)."""
    if not isinstance(mesh, LeafletMesh):
        raise ParameterError(f"template_map needs a LeafletMesh; got {type(mesh).__name__}")
    tpl = mesh.template
    edge, frac = _boundary_layout(tpl, mesh.h)
    K = len(edge)
    n = mesh.n_nodes
    boundary = np.arange(K)
    interior = np.arange(K, n)
    tm = TemplateMap(mesh, boundary, edge, frac, interior, np.zeros((n - K, K)))
    pb = np.asarray(jax.jit(tm.boundary_points)(tpl.r, tpl.a, tpl.b, tpl.alpha))
    err = float(np.max(np.abs(pb - mesh.points[:K]))) if K else 0.0
    if err > 1e-9 * max(1.0, tpl.height):
        raise MeshError(f"the mesh's boundary nodes are not where the template puts them "
                        f"(largest offset {err:.3e} mm); build it with mesh_leaflet")
    L = cot_laplacian(mesh.points, mesh.triangles)
    A = L[interior][:, interior].tocsc()
    B = L[interior][:, boundary].toarray()
    ext = -spla.splu(A).solve(B) if len(interior) else np.zeros((0, K))
    return dataclasses.replace(tm, extension=np.ascontiguousarray(ext))
