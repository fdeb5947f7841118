"""`simulate(scene)`: close a valve and measure its coaptation (the product's main job).

Steps (each reported to ``progress``): build the root, mesh the template, place the three
leaflets, close at the effective-height load (3 mmHg) from the placement, then at the
diastolic load (80 mmHg) from that state (`jaxvalve.valve.closure.close_valve`, the one closure
driver: both solves share one compiled function, since P is a traced parameter), and
measure the coaptation characteristics (docs/metrics.md) on both states.  Returns a `SimulationResult`.
"""
from __future__ import annotations

import dataclasses
import functools
import time
from typing import Any, Callable

import numpy as np

from .valve import model as V
from .valve.closure import SolveReport, close_valve
from .coaptation import annulus_level, coaptation_metrics
from .errors import ConvergenceError
from .geometry.leaflet_mesh import mesh_leaflet
from .scene import Scene
from .timing import compile_timer

__all__ = ["simulate", "SimulationResult", "SolveReport", "compile_timer", "measure"]


@dataclasses.dataclass(frozen=True)
class SimulationResult:
    """A closed valve and its coaptation.

    scene: the `Scene`.  valve: the `jaxvalve.valve.Valve` (meshes, root, placement).
    x (N, 3) mm: closed at ``scene.pressure``; x_he (N, 3) mm: closed at
    ``scene.he_pressure``.  metrics: `CoaptationResult` at the closing load; metrics_he:
    at the effective-height load (its ``h_e`` is the reported h_E).
    solves: (`SolveReport` at he_pressure, `SolveReport` at pressure).
    timings: seconds for 'setup' (root, mesh, placement), 'metrics' and 'total'.
    """

    scene: Scene
    valve: Any
    x: np.ndarray
    x_he: np.ndarray
    metrics: Any
    metrics_he: Any
    solves: tuple
    timings: dict

    @property
    def converged(self) -> bool:
        return all(s.converged for s in self.solves)

    @property
    def h_E(self) -> float:
        """Effective height (mm), measured at the effective-height load."""
        return self.metrics_he.h_e

    @functools.cached_property
    def warnings(self) -> tuple:
        """Findings about the design a surgeon would want flagged (str each; none is an
        error): a central coaptation point (the top of the three-leaflet zone, h_E) above
        every commissure, a sign of surplus tissue: the leaflets meet higher than the
        points they hang from.  None for a state that is not an equilibrium (h_E is
        measured at the effective-height load: its solve must have converged).  A closure
        that ended at a limit point gets the inflation analysis of its material
        (`jaxvalve.mechanics.inflation`): the bulge radius that explains the limit; or,
        for a material that stiffens, that the limit is the end of the branch followed,
        and whether its state is compressed past the stretch below which the material
        softens (StVK: 1/sqrt(3))."""
        out = []
        lim = [s for s in self.solves if s.result == "limit_point"]
        if lim:
            out.append(f"limit point: no equilibrium above {lim[0].limit_pressure:.3g} mmHg "
                       "on the branch followed; " + self._limit_analysis(lim[0]))
        heights = np.asarray(self.valve.root.commissure_heights, float)
        if (self.solves[0].converged and np.isfinite(self.h_E)
                and self.h_E > heights.max()):
            out.append(f"surplus tissue: the central coaptation point lies "
                       f"{self.h_E:.1f} mm above the annulus (h_E, at "
                       f"{self.scene.he_pressure:g} mmHg), above the commissures "
                       f"({heights.min():.1f}-{heights.max():.1f} mm): the leaflets meet "
                       f"higher than they hang")
        return tuple(out)

    def _limit_analysis(self, solve) -> str:
        """The material's analysis of a limit point (`warnings`)."""
        from .mechanics.inflation import compression_limit, inflation_limit
        from .valve.checks import triangle_checks
        material = self.scene.material()
        a = inflation_limit(material, self.scene.thickness)
        if a.exists:
            return a.describe(solve.limit_pressure)
        c = compression_limit(material)
        x = self.x_he if solve is self.solves[0] else self.x
        lam = (triangle_checks(self.valve.ref, self.valve.triangles, x).min_stretch
               if np.all(np.isfinite(x)) else float("nan"))
        text = (a.describe() + ", so this limit is not the membrane's inflation limit but "
                "the end of the branch the continuation followed")
        if c is not None and lam < c:
            text += (f"; its state is compressed to a principal stretch of {lam:.3f}, past "
                     f"the {c:.3f} below which {a.model} softens in compression (an "
                     "artefact of the material law: real tissue wrinkles)")
        return text + " (docs/limit-points.md)"

    def summary(self) -> dict:
        """The headline metrics (mm, %) of the valve."""
        m = self.metrics
        return dict(h_E=self.h_E, h_CC=m.h_cc, h_avr=m.h_avr_valve, NCCA_pct=100 * m.ncca_valve,
                    h=m.h, h_c=m.h_c, coaptation_area=float(np.sum(m.zone_area)))

    def leaflet(self, i: int, state: str = "closed"):
        """(points (n, 3) mm, triangles (m, 3)) of leaflet i in the state 'closed',
        'effective' (he_pressure), 'placed' or 'template' (z = 0)."""
        sl = self.valve.leaflet_slice(i)
        tri = self.valve.leaflet.triangles
        if state == "closed":
            return self.x[sl], tri
        if state == "effective":
            return self.x_he[sl], tri
        if state == "placed":
            return np.asarray(self.valve.x_start)[sl], tri
        if state == "template":
            p = self.valve.leaflet.points
            return np.column_stack([p, np.zeros(len(p))]), tri
        raise ValueError(f"state must be 'closed', 'effective', 'placed' or 'template'; "
                         f"got {state!r}")

    def as_dict(self) -> dict:
        """Everything as JSON-ready plain data (see `jaxvalve.io.report.metrics_json`)."""
        from .io.report import metrics_json
        return metrics_json(self)

    # plot helpers (matplotlib is imported lazily)
    def plot_valve(self, ax=None, **kw):
        from .io.plots import plot_valve
        return plot_valve(self, ax=ax, **kw)

    def plot_aortic_view(self, ax=None, **kw):
        from .io.plots import plot_aortic_view
        return plot_aortic_view(self, ax=ax, **kw)

    def plot_profiles(self, ax=None, **kw):
        from .io.plots import plot_profiles
        return plot_profiles(self, ax=ax, **kw)

    def plot_pair_heights(self, ax=None, **kw):
        from .io.plots import plot_pair_heights
        return plot_pair_heights(self, ax=ax, **kw)

    def write(self, out_dir, figures: bool = True):
        """Write metrics.json, one .vtu per leaflet and (optionally) PNG figures into
        ``out_dir``; returns the list of paths written."""
        from .io.report import write_outputs
        return write_outputs(self, out_dir, figures=figures)


def measure(valve, x, g_c):
    """The exact coaptation metrics (`CoaptationResult`) of the valve in state x (N, 3) mm,
    with the coaptation distance g_c mm, heights from the annulus level of x."""
    root = valve.root
    s0 = annulus_level(x, np.asarray(valve.problem.fixed), valve.body, root.axis, root.origin)
    return coaptation_metrics(x, valve.triangles, valve.body, np.asarray(valve.ref),
                              valve.free_edge, axis=root.axis, origin=root.origin,
                              annulus_level=s0, g_c=g_c)


def _quiet(msg):
    pass


def build_scene_valve(scene: Scene, say=_quiet):
    """The scene's `Valve`: root, template mesh at scene.h, placement (each step reported
    to ``say``)."""
    say("building the aortic root")
    root = scene.load_root()
    say(f"meshing the template (r={scene.r}, a={scene.a}, b={scene.b}, "
        f"alpha={scene.alpha}, h={scene.h} mm)")
    lmesh = mesh_leaflet(scene.template(), scene.h)
    say(f"placing 3 x {len(lmesh.triangles)} triangles in the root")
    return V.build_valve(root, lmesh)


def simulate(scene: Scene | None = None, *, progress: Callable[[str], None] | None = None,
             throw: bool = True, valve=None) -> SimulationResult:
    """Close the valve of ``scene`` (default: the benchmark `Scene()`) and measure it.

    progress: called with one line of text per phase (e.g. ``print``).
    throw: raise `ConvergenceError` (with the residual) when a solve did not converge;
    with throw=False the result is returned and ``result.converged`` is False.  A state
    the solver accepts is checked independently (`jaxvalve.valve.state_failure`): crossed
    leaflets or a collapsed or folded triangle make it not converged
    (``leaflets_cross``, ``inverted_triangles``: `jaxvalve.valve.STATE_FAILURES`).
    A state that is not finite raises `ConvergenceError` either way (it cannot be
    measured).  valve: a prebuilt `Valve` for this scene's root and template (skips the
    setup).  The closures are `jaxvalve.valve.closure.close_valve`'s.
    """
    scene = Scene() if scene is None else scene
    say = progress or _quiet
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    valve = build_scene_valve(scene, say) if valve is None else valve
    setup = time.perf_counter() - t0
    loads = close_valve(valve, scene, throw=throw, say=say)
    for ls in loads:
        if not np.all(np.isfinite(ls.x)):
            raise ConvergenceError(f"valve closure at {ls.report.pressure:g} mmHg produced "
                                   "non-finite positions", ls.solution)
    say("measuring coaptation")
    t0 = time.perf_counter()
    m_he = measure(valve, loads[0].x, scene.g_c)
    m = measure(valve, loads[1].x, scene.g_c)
    t_m = time.perf_counter() - t0
    timings = dict(setup=setup, metrics=t_m, total=time.perf_counter() - t_all)
    return SimulationResult(scene=scene, valve=valve, x=loads[1].x, x_he=loads[0].x,
                            metrics=m, metrics_he=m_he,
                            solves=tuple(ls.report for ls in loads), timings=timings)
