"""The one closure driver: a valve closed under its loads.

Every closure in jaxvalve runs through here: `simulate`, `simulate_batch` (whose batched
program makes each member's first attempt at each load, handed here as ``first``), the
optimiser's `Evaluator` and the stress suite.

* `close_load(valve, scene, p, x0, p_from=...)`: one load.  The engine's solve at p mmHg
  from x0 (`valve.close`: FIRE, then a Newton finish where FIRE stagnates, with the state
  check), and where it runs away or fails in a way a shorter load step may mend
  (`continuation.cut_on`), continuation in pressure from the equilibrium x0 at p_from,
  ending as ``limit_point`` where no equilibrium lies above a pressure
  (`continuation.ramp`).  Returns a `LoadSolve`: the `SolveReport`, the state, the solve
  that gave it (with its pair lists, for the adjoint) and the ramp.
* `close_valve(valve, scene)`: the scene's loads in turn (``he_pressure``, then
  ``pressure``), each from the state of the one before; a start past a Gent material's
  stretch limit is first settled at 0 mmHg under the limit-free law
  (`admissible_start`).  A load after one that did not converge (or ended at a limit
  point) is not solved: its report repeats the earlier outcome with 0 steps.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import jax
import numpy as np

from . import model as V
from ..solvers.continuation import Ramp, RampResult, cut_on, ramp
from ..errors import ConvergenceError, ParameterError
from ..scene import Scene
from ..solvers import RESULTS
from ..solvers.equilibrium import Engine
from ..timing import compile_timer

__all__ = ["SolveReport", "LoadSolve", "close_load", "close_valve", "path_name",
           "admissible_start"]


def _quiet(msg):
    pass


@dataclasses.dataclass(frozen=True)
class SolveReport:
    """One load: pressure (mmHg), result name, converged, steps, relative residual
    ||F_free|| / ||F_pressure||, wall time (s) and the part of it spent compiling.
    A load past the valve's limit point has result 'limit_point' and ``limit_pressure``,
    the highest pressure (mmHg) with an equilibrium, whose state and residual are
    reported instead (`jaxvalve.solvers.continuation`).  state_pressure (mmHg): the
    pressure of the state reported, where it is not ``pressure`` (a limit point, or a
    continuation that failed on the way).  cause: for a solve that did not converge, why
    in one line (else None).  path: "engine" (FIRE, then ``newton_steps`` Newton steps
    where FIRE stagnated) or "paper" (Algorithm 2.1)."""

    pressure: float
    result: str
    converged: bool
    steps: int
    residual: float
    wall_s: float = 0.0
    compile_s: float = 0.0
    limit_pressure: float | None = None
    state_pressure: float | None = None
    cause: str | None = None
    path: str | None = None
    newton_steps: int = 0

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
        newton = f" ({self.newton_steps} Newton)" if self.newton_steps else ""
        return (f"{'converged' if self.converged else self.result}{at}, residual "
                f"{self.residual:.2e}, {self.steps} steps{newton}{why}")

    def as_dict(self):
        d = dataclasses.asdict(self)
        d["solve_s"] = self.solve_s
        return d


@dataclasses.dataclass(frozen=True)
class LoadSolve:
    """The outcome of one load (`close_load`).

    report: `SolveReport`.  x (N, 3) mm, float64: the state reported (the equilibrium at
    ``report.state_pressure`` for a limit point).  solution: the `ValveSolution` that gave
    x, in the scene's precision (its pair lists serve the adjoint).  ramp: the
    `RampResult` (``history``: every solve of the continuation)."""

    report: SolveReport
    x: np.ndarray
    solution: Any
    ramp: RampResult

    @property
    def converged(self) -> bool:
        return self.report.converged

    @property
    def limit_point(self) -> bool:
        return self.report.result == "limit_point"


def path_name(scene: Scene) -> str:
    """The closure path of a scene: "engine" or "paper"."""
    return scene.solver


def _params(valve, scene, material, p, ref):
    params = valve.params(material, p, scene.contact_law(), scene.thickness,
                          np.deg2rad(scene.fibre_angle), scene.bending_law())
    return params if ref is None else params.replace(ref=ref)


def _cause(sol) -> str | None:
    """Why a solve did not converge, in one line (None where it did)."""
    if sol is None or sol.converged:
        return None
    newton = getattr(sol, "newton_steps", 0)
    if newton:
        return (f"FIRE stagnated, and Newton from its best state ended as {sol.status} "
                f"after {newton} steps")
    if sol.status in ("max_steps_reached", "stagnation"):
        return (f"FIRE ended as {sol.status} far from an equilibrium (its best residual "
                f"above {Engine.finish_below:g}), where no Newton finish is tried")
    return None


def close_load(valve, scene: Scene, pressure: float, x0, *, p_from: float = 0.0,
               material=None, ref=None, caps=None, first=None,
               say: Callable[[str], None] = _quiet) -> LoadSolve:
    """Close ``valve`` at ``pressure`` mmHg from x0 (N, 3) mm, an equilibrium at p_from
    mmHg (or the placement, p_from = 0), by the scene's method.

    material: the scene's material by default (a batch member's, a stiffness sample).
    ref: a mapped reference (N, 2|3) mm (`valve.close`).  caps: pair-list capacities to
    start from.  first: the first attempt at ``pressure`` from x0, already solved (a
    `ValveSolution`, state-checked; `simulate_batch`'s batched program).
    say: progress, one line per phase."""
    material = scene.material() if material is None else material
    solver = scene.make_solver()
    contact, bending = scene.contact_law(), scene.bending_law()
    pending = [first]
    held = [caps]

    def solve(p, x):
        given, pending[0] = pending[0], None
        if given is not None and p == pressure:
            return given
        sol = V.close(valve, material, p, solver=solver, contact=contact,
                      thickness=scene.thickness, fibre_angle=np.deg2rad(scene.fibre_angle),
                      bending=bending, x0=x, throw=False, check_state=True, caps=held[0],
                      ref=ref)
        held[0] = sol.caps if sol.caps is not None else held[0]
        return sol

    if first is None:
        say(f"closing at {pressure:g} mmHg ({scene.model}, {scene.solver})")
    with compile_timer() as ct:
        t0 = time.perf_counter()
        rr = ramp(solve, x0, pressure, p_from, Ramp.for_solver(solver), cut=cut_on(solver))
        sol, p_state = rr.final
        jax.block_until_ready(sol.x)
        wall = time.perf_counter() - t0
    if len(rr.history) > 1:
        say("  continuation: " + ", ".join(f"{q:.3g} mmHg {r} ({n} steps)"
                                           for q, r, n, _ in rr.history))
    status = RESULTS.successful.name if rr.converged else rr.status
    x = np.asarray(sol.x, np.float64)
    rep = SolveReport(pressure=float(pressure), result=status, converged=rr.converged,
                      steps=rr.steps, residual=float(sol.stats.residual), wall_s=wall,
                      compile_s=min(ct.seconds, wall),
                      limit_pressure=rr.pressure if rr.limit_point else None,
                      state_pressure=float(p_state),
                      cause=None if rr.converged or rr.limit_point else _cause(sol),
                      path=path_name(scene), newton_steps=getattr(sol, "newton_steps", 0))
    if first is None or len(rr.history) > 1:
        say(f"  {rep.describe()}; {rep.solve_s:.2f} s (+{rep.compile_s:.1f} s compile)")
    return LoadSolve(report=rep, x=x, solution=sol, ramp=rr)


def _skipped(prev: LoadSolve, p, why, say) -> LoadSolve:
    say(f"closing at {p:g} mmHg: skipped, {why}")
    rep = dataclasses.replace(prev.report, pressure=float(p), steps=0, wall_s=0.0,
                              compile_s=0.0, newton_steps=0)
    return dataclasses.replace(prev, report=rep)


def _worst_margin(valve, material, x) -> float:
    """The smallest `Material.stretch_margin` over the triangles of x (N, 3) mm: positive
    where the law's energy is finite everywhere."""
    from ..geometry.mesh import cauchy_green_np
    C = cauchy_green_np(x, valve.triangles, valve.ref)
    return float(np.min(np.asarray(material.stretch_margin(C))))


def admissible_start(valve, scene: Scene, x, *, material=None, say=_quiet):
    """A start inside the material's stretch limit: x itself where the law's energy is
    finite there (every law without a limit; Gent where no triangle of x reaches Jm),
    else the placement settled at P = 0 (`model.settle`) under the law's limit-free
    relative (`Material.limit_free`: neo-Hookean with Gent's mu).  The placement is a
    harmonic surface, not an equilibrium: template (b) of the stress suite places a
    triangle at I1 + 1/I2 - 3 = 0.44, and settled it is at 0.023, so a Gent valve with
    Jm = 0.1 or 0.3 has equilibria that a solve from the placement never reaches (its
    first step is past the limit).  Raises `ParameterError` naming Jm and its range where
    even the settled leaflets pass the limit: the leaflets at rest already carry more
    stretch than Jm allows.
    Returns x, or the settled state (N, 3) in x's dtype."""
    material = scene.material() if material is None else material
    free = material.limit_free()
    if free is material or _worst_margin(valve, material, x) > 0:
        return x
    from .checks import gent_invariant
    g_x = float(np.max(gent_invariant(valve.ref, valve.triangles, x)))
    say(f"the start passes the {material.name} stretch limit (max (I1 + 1/I2 - 3) = "
        f"{g_x:.3g} >= Jm = {float(material.Jm):g}): settling the placement at 0 mmHg "
        f"under the limit-free law ({free.name}, the same mu)")
    settled, sol = V.settle(valve, free, thickness=scene.thickness)
    y = np.asarray(settled.x_start, np.float64)
    g_y = float(np.max(gent_invariant(valve.ref, valve.triangles, y)))
    if not _worst_margin(valve, material, y) > 0:
        raise ParameterError(
            f"Gent Jm = {float(material.Jm):g} lies below the stretch that the sewn leaflets "
            f"carry at rest: settled without pressure under the limit-free law ({free.name},"
            f" the same mu) their most stretched triangle has I1 + 1/I2 - 3 = {g_y:.3g}, so "
            f"for this template and root Jm must exceed {g_y:.3g}")
    say(f"  settled: {sol.describe()}; max (I1 + 1/I2 - 3) = {g_y:.3g}")
    return y.astype(np.asarray(x).dtype)


def close_valve(valve, scene: Scene, *, material=None, x0=None, pressures=None, caps=None,
                first=(), done=(), throw: bool = False,
                say: Callable[[str], None] = _quiet) -> tuple:
    """The valve closed under ``pressures`` mmHg in turn (default the scene's
    (he_pressure, pressure)), each load from the state of the one before (`close_load`;
    the first from x0, default ``valve.x_start``, settled first where it passes the
    material's stretch limit, `admissible_start`).  Returns one `LoadSolve` a load.

    first: per load, a first attempt already solved (`close_load`); the attempt at a
    later load is used only where the load before ended with its own first attempt (the
    batched program solved from that state).  done: the first loads' `LoadSolve`s,
    already closed by this driver (the stress suite's shared 3 mmHg closure), taken as
    they are.  throw: raise `ConvergenceError` at the first load that did not converge
    (its ``solution`` is the `ValveSolution`)."""
    pressures = ((scene.he_pressure, scene.pressure) if pressures is None
                 else tuple(float(p) for p in pressures))
    material = scene.material() if material is None else material
    x = np.asarray(valve.x_start if x0 is None else x0, scene.dtype)
    if x0 is not None and not done:
        crossed = V.leaflet_crossings(valve, x)
        if len(crossed):
            raise ParameterError(
                f"x0 has {len(crossed)} pairs of crossing triangles: the barrier contact "
                f"closes leaflets that are apart (start from the placement, x0=None, or "
                f"from a closed state of this valve)")
    if not done:
        y = admissible_start(valve, scene, x, material=material, say=say)
        if y is not x:          # the batched first attempts started past the limit
            x, first = y, ()
    out, p_prev = list(done), 0.0
    if done:
        x, p_prev = np.asarray(done[-1].solution.x), float(done[-1].report.state_pressure)
        caps = done[-1].solution.caps
    for i, p in enumerate(pressures):
        if i < len(done):
            continue
        prev = out[-1] if out else None
        if prev is not None and prev.limit_point:
            out.append(_skipped(prev, p, "above the limit point", say))
            continue
        if prev is not None and not prev.converged:
            out.append(_skipped(prev, p, "the load before it did not converge", say))
            continue
        f = first[i] if i < len(first) else None
        if prev is not None and len(prev.ramp.history) > 1:
            f = None          # the batched attempt started from another state
        ls = close_load(valve, scene, p, x, p_from=p_prev if p_prev < p else 0.0,
                        material=material, caps=caps, first=f, say=say)
        out.append(ls)
        x, p_prev = np.asarray(ls.solution.x), float(ls.report.state_pressure)
        caps = ls.solution.caps or caps
    if throw:
        for ls, p in zip(out, pressures):
            if not ls.converged:
                raise ConvergenceError(f"valve closure at {p:g} mmHg did not converge: "
                                       f"{ls.report.describe()}", ls.solution)
    return tuple(out)
