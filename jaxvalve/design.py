"""The differentiable chain from template parameters to a valve's reference state.

theta = (r, a, b, alpha) (mm, mm, mm, degrees) determines

* the flat reference nodes of each leaflet (`template_map.TemplateMap`, fixed topology);
* the sutured-edge length L = 2a + pi r alpha / 180, and with it the suturing paths: a
  patient root's paths are data (`FixedPaths`), while the benchmark root is fitted to L
  (`BenchmarkPaths`: its commissure height H solves length(H) = L, differentiated
  implicitly, dH/dtheta = (dL/dtheta) / length'(H));
* the positions of the sutured nodes, uniformly by arc length along the paths (placement,
  step 2), at the fractions of A-B-C-D that the map gives them.

`ValveDesign(valve, tmap, paths)` bundles these for one valve; ``ref(theta)`` and
``x_fixed(theta)`` are jax.numpy functions, so `jax.grad` of anything computed from an
equilibrium (`equilibrium.solve` is differentiated by its adjoint) reaches theta.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from .errors import ParameterError
from .placement import leaflet_frame
from .root import _unit_path
from .template_map import TemplateMap

__all__ = ["along_path", "sutured_length", "FixedPaths", "BenchmarkPaths", "ValveDesign",
           "paths_for"]


def sutured_length(r, a, alpha):
    """Length of A-B-C-D (mm): 2a + pi r alpha / 180 (differentiable)."""
    return 2.0 * a + math.pi * r * alpha / 180.0


def along_path(path, t):
    """Points (K, 3) at arc-length fractions t (K,) in [0, 1] of the polyline path (P, 3);
    differentiable in both path and t (jax.numpy version of `placement.along_polyline`)."""
    seg = jnp.linalg.norm(jnp.diff(path, axis=0), axis=1)
    s = jnp.concatenate([jnp.zeros(1, path.dtype), jnp.cumsum(seg)])
    u = jnp.clip(t, 0.0, 1.0) * s[-1]
    k = jnp.clip(jnp.searchsorted(jax.lax.stop_gradient(s), jax.lax.stop_gradient(u),
                                  side="right") - 1, 0, path.shape[0] - 2)
    w = (u - s[k]) / seg[k]
    return path[k] + w[:, None] * (path[k + 1] - path[k])


@dataclasses.dataclass(frozen=True)
class FixedPaths:
    """The suturing paths of a given root (3 x (P_i, 3) mm), independent of theta."""

    paths: tuple

    def __call__(self, L):
        return tuple(jnp.asarray(p) for p in self.paths)


@dataclasses.dataclass(frozen=True)
class BenchmarkPaths:
    """The benchmark root's paths as functions of the sutured length L (mm).

    A path samples (r(s) cos th(s), r(s) sin th(s), H zeta(s)); only the commissure height
    H depends on L (`root.benchmark_root`).  xy (3, P, 2), zeta (P,): the fixed parts;
    H_range: the accepted heights (mm)."""

    xy: Any
    zeta: Any
    H_range: tuple

    @classmethod
    def from_root(cls, root):
        d = root.dimensions
        if d.get("fitted_parameter") != "commissure_height":
            raise ParameterError("BenchmarkPaths needs a root made by benchmark_root")
        xy = np.stack([np.asarray(p)[:, :2] for p in root.paths])
        _, zeta = _unit_path(d["path_exponent"], d["n_path"])
        return cls(xy, zeta, tuple(d["height_range_mm"]))

    def length(self, H):
        """Polyline length (mm) of one path at commissure height H."""
        a2 = jnp.sum(jnp.diff(jnp.asarray(self.xy[0]), axis=0) ** 2, axis=1)
        b2 = jnp.diff(jnp.asarray(self.zeta)) ** 2
        return jnp.sum(jnp.sqrt(a2 + H * H * b2))

    def height(self, L, iterations=60):
        """Commissure height H (mm) with length(H) = L: safeguarded Newton on the host
        bracket, then one Newton step with derivatives (exact implicit gradient)."""
        lo, hi = self.H_range
        Lc = jax.lax.stop_gradient(L)
        dlen = jax.grad(self.length)

        def body(_, H):
            Hn = H - (self.length(H) - Lc) / dlen(H)
            return jnp.clip(Hn, lo, hi)

        H = jax.lax.fori_loop(0, iterations, body, jnp.asarray(0.5 * (lo + hi), Lc.dtype))
        H = jax.lax.stop_gradient(H)
        return H - (self.length(H) - L) / dlen(H)

    def __call__(self, L):
        H = self.height(L)
        z = H * jnp.asarray(self.zeta)
        return tuple(jnp.concatenate([jnp.asarray(xy), z[:, None]], axis=1) for xy in self.xy)


def paths_for(root):
    """`BenchmarkPaths` for a benchmark root, else `FixedPaths`."""
    if root.dimensions and root.dimensions.get("fitted_parameter") == "commissure_height":
        return BenchmarkPaths.from_root(root)
    return FixedPaths(tuple(np.asarray(p) for p in root.paths))


@dataclasses.dataclass(frozen=True)
class ValveDesign:
    """theta -> (reference nodes, sutured positions) of a three-leaflet `Valve`.

    valve: built from ``tmap.base`` (`valve.build_valve`); tmap: its `TemplateMap`;
    paths: `FixedPaths` or `BenchmarkPaths` (default from the root, `paths_for`)."""

    valve: Any
    tmap: TemplateMap
    paths: Any = None
    mirror: tuple = ()

    @classmethod
    def build(cls, valve, tmap, paths=None):
        if valve.nodes_per_leaflet != tmap.base.n_nodes:
            raise ParameterError("the valve was not built from the template map's mesh")
        root = valve.root
        mirror = tuple(leaflet_frame(root.commissures[i], root.commissures[(i + 1) % 3],
                                     root.axis, root.origin)[3] for i in range(3))
        return cls(valve, tmap, paths_for(root) if paths is None else paths, mirror)

    def ref(self, theta):
        """Reference nodes (3n, 2) mm of the three leaflets for theta = (r, a, b, alpha)."""
        p = self.tmap.points(*theta)
        return jnp.concatenate([p, p, p])

    def sutured_positions(self, theta):
        """(3, n_s, 3) mm: the sutured nodes of each leaflet on its path."""
        r, a, _, alpha = theta
        t = self.tmap.sutured_t(r, a, alpha)
        paths = self.paths(sutured_length(r, a, alpha))
        return jnp.stack([along_path(paths[i], 1.0 - t if self.mirror[i] else t)
                          for i in range(3)])

    def x_fixed(self, theta, x_free=None):
        """Positions (3n, 3) mm: sutured nodes from theta, the others from ``x_free``
        (default the valve's start; they only seed the solve)."""
        n = self.valve.nodes_per_leaflet
        sut = np.asarray(self.tmap.base.sutured)
        idx = np.concatenate([sut + i * n for i in range(3)])
        x = jnp.asarray(self.valve.x_start if x_free is None else x_free)
        return x.at[idx].set(self.sutured_positions(theta).reshape(-1, 3))
