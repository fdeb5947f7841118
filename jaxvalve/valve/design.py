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
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

from ..errors import ParameterError
from ..mechanics.materials import _concrete
from .placement import along_path, leaflet_frame
from ..geometry.root import _unit_path, length_terms, path_length
from ..geometry.template import Template, sutured_length
from ..geometry.template_map import TemplateMap

__all__ = ["check_theta", "FixedPaths", "BenchmarkPaths", "ValveDesign",
           "paths_for"]


def check_theta(theta):
    """Raise `ParameterError` (naming the parameter and its bound) for a concrete theta =
    (r, a, b, alpha) that is not a valid template; traced values are not checked."""
    if all(_concrete(v) for v in theta):
        Template(*(float(v) for v in theta))
    return theta


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
    terms: tuple

    @classmethod
    def from_root(cls, root):
        d = root.dimensions
        if not d or d.get("fitted_parameter") != "commissure_height":
            raise ParameterError("BenchmarkPaths needs a root made by benchmark_root")
        xy = np.stack([np.asarray(p)[:, :2] for p in root.paths])
        s, zeta = _unit_path(d["path_exponent"], d["n_path"])
        terms = length_terms(s, zeta, d["annulus_radius"], d["stj_radius"])
        return cls(xy, zeta, tuple(d["height_range_mm"]), terms)

    def length(self, H):
        """Polyline length (mm) of one path at commissure height H (`root.path_length`)."""
        return path_length(tuple(jnp.asarray(t) for t in self.terms), H, jnp)

    def height(self, L, iterations=40):
        """Commissure height H (mm) with length(H) = L: Newton (length is convex and
        increasing in H) from the top of the accepted range, then one Newton step with
        derivatives, so that dH/dL = 1 / length'(H) exactly.  A concrete L outside the
        accepted range raises `ParameterError`; a traced one gives NaN."""
        lo, hi = self.H_range
        L_lo, L_hi = (float(path_length(self.terms, H)) for H in (lo, hi))   # host
        if _concrete(L) and not L_lo <= float(L) <= L_hi:
            raise ParameterError(
                f"sutured_length = {float(L):.6g} mm has no benchmark suturing path: the "
                f"accepted range is [{L_lo:.4f}, {L_hi:.4f}] mm (commissure heights "
                f"[{lo:g}, {hi:g}] mm)")
        Lc = jax.lax.stop_gradient(L)
        dlen = jax.grad(self.length)

        def body(_, H):
            return jnp.clip(H - (self.length(H) - Lc) / dlen(H), lo, hi)

        H = jax.lax.stop_gradient(
            jax.lax.fori_loop(0, iterations, body, jnp.asarray(hi, jnp.result_type(Lc, float))))
        H = H - (self.length(H) - L) / dlen(H)
        return jnp.where((Lc >= L_lo) & (Lc <= L_hi), H, jnp.nan)

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
        p = self.tmap.points(*check_theta(theta))
        return jnp.concatenate([p, p, p])

    def sutured_positions(self, theta):
        """(3, n_s, 3) mm: the sutured nodes of each leaflet on its path."""
        r, a, _, alpha = check_theta(theta)
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
