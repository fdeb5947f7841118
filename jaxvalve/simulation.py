"""`simulate(scene)`: close a valve and measure its coaptation (the product's main job).

Steps (each reported to ``progress``): build the root, mesh the template, place the three
leaflets, close at the effective-height load (3 mmHg) from the placement, then at the
diastolic load (80 mmHg) from that state (a two-step continuation in P: both solves share
one compiled function, since P is a traced parameter), and measure the coaptation
characteristics (DESIGN.md) on both states.  Returns a `SimulationResult`.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import jax
import numpy as np

from . import valve as V
from .coaptation import annulus_level, coaptation_metrics
from .continuation import Ramp, cut_on, ramp
from .errors import ConvergenceError
from .leaflet_mesh import mesh_leaflet
from .scene import Scene
from .solvers import RESULTS
from .stall import closure_cause

__all__ = ["simulate", "SimulationResult", "SolveReport", "compile_timer", "measure"]


class compile_timer:
    """Context manager that sums JAX's tracing, lowering and XLA compile durations (s)
    reported through `jax.monitoring` while it is open."""

    _EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
               "/jax/core/compile/jaxpr_to_mlir_module_duration",
               "/jax/core/compile/backend_compile_duration")
    _active: list = []
    _registered = False

    def __init__(self):
        self.seconds = 0.0

    @classmethod
    def _listener(cls, event, duration, **kw):
        if event in cls._EVENTS:
            for t in cls._active:
                t.seconds += duration

    def __enter__(self):
        if not compile_timer._registered:
            jax.monitoring.register_event_duration_secs_listener(compile_timer._listener)
            compile_timer._registered = True
        compile_timer._active.append(self)
        return self

    def __exit__(self, *exc):
        compile_timer._active.remove(self)
        return False


@dataclasses.dataclass(frozen=True)
class SolveReport:
    """One load: pressure (mmHg), result name, converged, steps, relative residual
    ||F_free|| / ||F_pressure||, wall time (s) and the part of it spent compiling.
    A load past the valve's limit point has result 'limit_point' and ``limit_pressure``,
    the highest pressure (mmHg) with an equilibrium, whose state and residual are
    reported instead (`jaxvalve.continuation`).  state_pressure (mmHg): the pressure of
    the state reported, where it is not ``pressure`` (a limit point, or a continuation
    that failed on the way).  cause: for a solve stopped at its step cap, whether the
    force jumps where it stopped (`jaxvalve.stall`), else None."""

    pressure: float
    result: str
    converged: bool
    steps: int
    residual: float
    wall_s: float
    compile_s: float
    limit_pressure: float | None = None
    state_pressure: float | None = None
    cause: str | None = None

    @property
    def solve_s(self):
        """Wall time without compilation (s)."""
        return max(self.wall_s - self.compile_s, 0.0)

    def describe(self) -> str:
        """One line: the outcome at this load."""
        if self.result == "limit_point":
            return (f"limit_point: no equilibrium above {self.limit_pressure:.3g} mmHg "
                    f"(state shown at {self.limit_pressure:.3g} mmHg, residual "
                    f"{self.residual:.2e}, {self.steps} steps)")
        at = ("" if self.state_pressure in (None, self.pressure)
              else f" (state at {self.state_pressure:.3g} mmHg)")
        why = f"; {self.cause}" if self.cause else ""
        return (f"{'converged' if self.converged else self.result}{at}, residual "
                f"{self.residual:.2e}, {self.steps} steps{why}")

    def as_dict(self):
        d = dataclasses.asdict(self)
        d["solve_s"] = self.solve_s
        return d


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
        """Everything as JSON-ready plain data (see `jaxvalve.report.metrics_json`)."""
        from .report import metrics_json
        return metrics_json(self)

    # plot helpers (matplotlib is imported lazily)
    def plot_valve(self, ax=None, **kw):
        from .plots import plot_valve
        return plot_valve(self, ax=ax, **kw)

    def plot_profiles(self, ax=None, **kw):
        from .plots import plot_profiles
        return plot_profiles(self, ax=ax, **kw)

    def plot_pair_heights(self, ax=None, **kw):
        from .plots import plot_pair_heights
        return plot_pair_heights(self, ax=ax, **kw)

    def write(self, out_dir, figures: bool = True):
        """Write metrics.json, one .vtu per leaflet and (optionally) PNG figures into
        ``out_dir``; returns the list of paths written."""
        from .report import write_outputs
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


def _swing_shut(valve, scene, material, bending, x, say):
    """The barrier path's start (its time after compilation: ``timings['start']``): the
    valve swung shut at the lower load by the default path (FIRE on the penalty contact,
    to a relative residual of at most 1e-4), where that closure converges to a state with
    no crossing and every barrier distance positive; else ``x`` (the placement).
    Projected Newton from the open valve meets the fold limit of its line search at once
    on soft leaflets (Table 4: no progress in 500 iterations), while FIRE's dynamics
    swing them shut; from FIRE's state, Newton re-settles the valve on the barrier in a
    few steps.  The final states are equilibria of the barrier law either way."""
    from .contact.ipc_pairs import build_pairs
    start = scene.replace(contact="smooth", solver="fire", rtol=max(scene.rtol, 1e-4))
    say(f"swinging shut at {scene.he_pressure:g} mmHg (fire solver, smooth contact), the "
        "start of the barrier closures")
    t0 = time.perf_counter()
    sol = V.close(valve, material, scene.he_pressure, solver=start.make_solver(),
                  contact=start.contact_law(), thickness=scene.thickness,
                  fibre_angle=np.deg2rad(scene.fibre_angle), bending=bending, x0=x,
                  throw=False, check_state=True)
    y = np.asarray(sol.x, np.float64)
    ok = (sol.converged and np.all(np.isfinite(y))
          and build_pairs(valve.barrier_topology, y, 1.0).min_distance > 0)
    say(f"  {sol.describe()}; {time.perf_counter() - t0:.2f} s"
        + ("" if ok else "; the barrier closures start from the placement instead"))
    return y.astype(x.dtype) if ok else x


def simulate(scene: Scene | None = None, *, progress: Callable[[str], None] | None = None,
             throw: bool = True, valve=None) -> SimulationResult:
    """Close the valve of ``scene`` (default: the benchmark `Scene()`) and measure it.

    progress: called with one line of text per phase (e.g. ``print``).
    throw: raise `ConvergenceError` (with the residual) when a solve did not converge;
    with throw=False the result is returned and ``result.converged`` is False.  A state
    the solver accepts is checked independently (`jaxvalve.valve.state_failure`): crossed
    leaflets or a collapsed or folded triangle make it not converged
    (``leaflets_cross``, ``inverted_triangles``: `jaxvalve.valve.STATE_FAILURES`).
    valve: a prebuilt `Valve` for this scene's root and template (skips the setup).
    """
    scene = Scene() if scene is None else scene
    say = progress or _quiet
    t_all = time.perf_counter()
    t0 = time.perf_counter()
    valve = build_scene_valve(scene, say) if valve is None else valve
    setup = time.perf_counter() - t0
    material, contact, solver = scene.material(), scene.contact_law(), scene.make_solver()
    bending = scene.bending_law()
    reports, states = [], []
    x = np.asarray(valve.x_start, scene.dtype)
    p_prev, limit = 0.0, None
    start_s = 0.0
    if scene.contact == "barrier":
        with compile_timer() as ct:
            t0 = time.perf_counter()
            x = _swing_shut(valve, scene, material, bending, x, say)
            start_s = time.perf_counter() - t0
        start_s = max(start_s - ct.seconds, 0.0)

    def close(p, x0):
        return V.close(valve, material, p, solver=solver, contact=contact,
                       thickness=scene.thickness, fibre_angle=np.deg2rad(scene.fibre_angle),
                       bending=bending, x0=x0, throw=False, check_state=True)

    for p in (scene.he_pressure, scene.pressure):
        if limit is not None:        # the lower load passed the limit point: so does this
            reports.append(dataclasses.replace(reports[-1], pressure=float(p), steps=0,
                                               wall_s=0.0, compile_s=0.0))
            states.append(states[-1])
            say(f"closing at {p:g} mmHg: skipped, above the limit point")
            continue
        say(f"closing at {p:g} mmHg ({scene.model}, {scene.solver} solver, {scene.contact} "
            "contact)")
        with compile_timer() as ct:
            t0 = time.perf_counter()
            # one solve at p; where it runs away, continuation in pressure from p_prev
            rr = ramp(close, x, p, p_prev, Ramp.for_solver(solver), cut=cut_on(solver))
            sol, p_state = rr.final
            jax.block_until_ready(sol.x)
            wall = time.perf_counter() - t0
        if len(rr.history) > 1:
            say("  continuation: " + ", ".join(f"{q:.3g} mmHg {r} ({n} steps)"
                                               for q, r, n, _ in rr.history))
        limit = rr.pressure if rr.limit_point else None
        status = RESULTS.successful.name if rr.converged else rr.status
        rep = SolveReport(pressure=float(p), result=status,
                          converged=rr.converged, steps=rr.steps,
                          residual=float(sol.stats.residual), wall_s=wall,
                          compile_s=min(ct.seconds, wall), limit_pressure=limit,
                          state_pressure=p_state,
                          cause=closure_cause(valve, scene, material, status, p_state,
                                              sol.x))
        say(f"  {rep.describe()}; {rep.solve_s:.2f} s (+{rep.compile_s:.1f} s compile)")
        if throw and not rep.converged:
            raise ConvergenceError(f"valve closure at {p:g} mmHg did not converge: "
                                   f"{rep.describe()}", sol)
        x_new = np.asarray(sol.x)
        x = x_new
        if not np.all(np.isfinite(x)):
            raise ConvergenceError(f"valve closure at {p:g} mmHg produced non-finite "
                                   "positions", sol)
        reports.append(rep)
        states.append(x.astype(np.float64))
        p_prev = float(p)
    say("measuring coaptation")
    t0 = time.perf_counter()
    m_he = measure(valve, states[0], scene.g_c)
    m = measure(valve, states[1], scene.g_c)
    t_m = time.perf_counter() - t0
    timings = dict(setup=setup, metrics=t_m, total=time.perf_counter() - t_all,
                   start=start_s)
    return SimulationResult(scene=scene, valve=valve, x=states[1], x_he=states[0], metrics=m,
                            metrics_he=m_he, solves=tuple(reports), timings=timings)
