"""The one closure driver: a valve closed under its loads.

Every closure in jaxvalve runs through here: `simulate`, `simulate_batch` (whose batched
program makes each member's first attempt at each load, handed here as ``first``), the
optimiser's `Evaluator` and the stress suite.

* `close_load(valve, scene, p, x0, p_from=...)`: one load.  The solve at p mmHg from x0
  (`valve.close`, with its state check: crossed leaflets, folded or collapsed
  triangles); where it runs away, or fails in a way its solver declares a load step too
  long (`continuation.cut_on`), continuation in pressure from the equilibrium x0 at
  p_from, ending as ``limit_point`` where no equilibrium lies above a pressure
  (`continuation.ramp`, with the step budget `Ramp.for_solver`); for a solve stopped at
  its step cap, the stall probe's verdict (`stall.stopped_cause`).  Returns a
  `LoadSolve`: the `SolveReport`, the state, the solve that gave it (with its contact
  pair list, for the adjoint) and the ramp.
* `close_valve(valve, scene)`: the scene's loads in turn (``he_pressure``, then
  ``pressure``), each from the state of the one before; on the barrier path the valve is
  first swung shut (`swing_shut`); a start past a Gent material's stretch limit is first
  settled at 0 mmHg under the limit-free law (`admissible_start`).  A load above a limit
  point, or after a state that is not finite, is not solved: its report repeats the
  earlier outcome with 0 steps.
  **Fallback** (``scene.fallback``, on by default): where a load on the smooth penalty
  law fails for any reason but a limit point (a step cap, crossed leaflets, a folded
  triangle, a state that is not finite ...), the valve is closed again, every load, on
  the barrier law by the projected Newton solver (`fall_back`), starting from the
  smooth law's state at the first load where that state is separated (no crossing,
  every barrier distance positive).  Both loads of a result then come from one contact
  law, and each report names the path that closed it (``path``) and what failed before
  (``fallback``).  FIRE on the smooth law is the fast path (the benchmark valve closes
  on it in 1-2 s at h = 1.5 mm); the barrier path closes the soft valves on which it
  stalls (the paper's Table 4) but is several times slower, so it runs only where it is
  needed.  A limit point is the membrane's, not the contact law's: no fallback there.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Any, Callable

import jax
import numpy as np

from . import model as V
from ..solvers.continuation import Ramp, RampResult, cut_on, full_solver, ramp
from ..errors import ConvergenceError, ParameterError
from ..scene import Scene
from ..solvers import RESULTS
from ..solvers.stall import stopped_cause
from ..timing import compile_timer

__all__ = ["SolveReport", "LoadSolve", "close_load", "close_valve", "swing_shut",
           "watched_swing", "fall_back", "separated", "path_name", "admissible_start"]


def _quiet(msg):
    pass


@dataclasses.dataclass(frozen=True)
class SolveReport:
    """One load: pressure (mmHg), result name, converged, steps, relative residual
    ||F_free|| / ||F_pressure||, wall time (s) and the part of it spent compiling.
    A load past the valve's limit point has result 'limit_point' and ``limit_pressure``,
    the highest pressure (mmHg) with an equilibrium, whose state and residual are
    reported instead (`jaxvalve.solvers.continuation`).  state_pressure (mmHg): the pressure of
    the state reported, where it is not ``pressure`` (a limit point, or a continuation
    that failed on the way).  cause: for a solve stopped at its step cap, whether the
    force jumps where it stopped (`jaxvalve.solvers.stall`), else None.  path: the solver and
    contact law that closed it ("fire+smooth", "newton+barrier", ...).  fallback: where
    the barrier path closed a load after the scene's own path failed
    (`jaxvalve.valve.closure`, "Fallback"), what failed there (one line), else None; wall_s
    and compile_s then include the failed attempt's."""

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
    fallback: str | None = None

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
        fb = (f" [{self.path}, after {self.fallback}]" if self.fallback else "")
        return (f"{'converged' if self.converged else self.result}{at}, residual "
                f"{self.residual:.2e}, {self.steps} steps{why}{fb}")

    def as_dict(self):
        d = dataclasses.asdict(self)
        d["solve_s"] = self.solve_s
        return d


@dataclasses.dataclass(frozen=True)
class LoadSolve:
    """The outcome of one load (`close_load`).

    report: `SolveReport`.  x (N, 3) mm, float64: the state reported (the equilibrium at
    ``report.state_pressure`` for a limit point).  solution: the `ValveSolution` that gave
    x, in the scene's precision (its pair list serves the adjoint).  ramp: the
    `RampResult` (``history``: every solve of the continuation).  start_s: seconds, after
    compilation, spent swinging the valve shut before this load (barrier path)."""

    report: SolveReport
    x: np.ndarray
    solution: Any
    ramp: RampResult
    start_s: float = 0.0

    @property
    def converged(self) -> bool:
        return self.report.converged

    @property
    def limit_point(self) -> bool:
        return self.report.result == "limit_point"


def path_name(scene: Scene) -> str:
    """The closure path of a scene, "<solver>+<contact>" (e.g. "fire+smooth")."""
    return f"{scene.solver}+{scene.contact}"


def _params(valve, scene, material, p, ref):
    params = valve.params(material, p, scene.contact_law(), scene.thickness,
                          np.deg2rad(scene.fibre_angle), scene.bending_law())
    return params if ref is None else params.replace(ref=ref)


def close_load(valve, scene: Scene, pressure: float, x0, *, p_from: float = 0.0,
               material=None, ref=None, nbrs=None, whole_lists: bool = False, first=None,
               hint: float | None = None, say: Callable[[str], None] = _quiet) -> LoadSolve:
    """Close ``valve`` at ``pressure`` mmHg from x0 (N, 3) mm, an equilibrium at p_from
    mmHg (or the placement, p_from = 0), by the scene's law and solver.

    material: the scene's material by default (a batch member's, a stiffness sample).
    ref: a mapped reference (N, 2|3) mm (`valve.close`).  nbrs: the contact pair list
    every solve starts from (e.g. an empty one of larger capacity).  whole_lists:
    `equilibrium.solve`'s.  first: the first attempt at ``pressure`` from x0, already
    solved (a `ValveSolution`, state-checked; `simulate_batch`'s batched program).
    hint: a pressure at which another path ran away on this valve (`continuation.ramp`).
    say: progress, one line per phase."""
    material = scene.material() if material is None else material
    solver = scene.make_solver()
    contact, bending = scene.contact_law(), scene.bending_law()
    pending = [first]

    def solve(p, x, solver=solver):
        given, pending[0] = pending[0], None
        if given is not None and p == pressure:
            return given
        return V.close(valve, material, p, solver=solver, contact=contact,
                       thickness=scene.thickness, fibre_angle=np.deg2rad(scene.fibre_angle),
                       bending=bending, x0=x, throw=False, check_state=True, nbrs=nbrs,
                       ref=ref, whole_lists=whole_lists)

    # a solver's early stop (the barrier Newton's patience): before the ramp ends on such a
    # stop it solves to the target without it, and after a runaway it brackets the
    # limit point without it (`continuation.ramp`'s confirm)
    full = full_solver(solver)

    if first is None:
        say(f"closing at {pressure:g} mmHg ({scene.model}, {scene.solver} solver, "
            f"{scene.contact} contact)")
    with compile_timer() as ct:
        t0 = time.perf_counter()
        rr = ramp(solve, x0, pressure, p_from, Ramp.for_solver(solver), cut=cut_on(solver),
                  confirm=None if full is None else (
                      lambda p, x, max_steps: solve(p, x, _capped(full, max_steps))),
                  hint=hint)
        sol, p_state = rr.final
        jax.block_until_ready(sol.x)
        wall = time.perf_counter() - t0
    if len(rr.history) > 1:
        say("  continuation: " + ", ".join(f"{q:.3g} mmHg {r} ({n} steps)"
                                           for q, r, n, _ in rr.history))
    status = RESULTS.successful.name if rr.converged else rr.status
    x = np.asarray(sol.x, np.float64)
    cause = stopped_cause(valve.problem, _params(valve, scene, material, p_state, ref),
                          status, x, skin=valve.skin, precision=scene.precision,
                          fold_bound=not (getattr(contact, "barrier", False)
                                          and valve.barrier_topology.self_contact))
    rep = SolveReport(pressure=float(pressure), result=status, converged=rr.converged,
                      steps=rr.steps, residual=float(sol.stats.residual), wall_s=wall,
                      compile_s=min(ct.seconds, wall),
                      limit_pressure=rr.pressure if rr.limit_point else None,
                      state_pressure=float(p_state), cause=cause,
                      path=path_name(scene))
    if first is None or len(rr.history) > 1:
        say(f"  {rep.describe()}; {rep.solve_s:.2f} s (+{rep.compile_s:.1f} s compile)")
    return LoadSolve(report=rep, x=x, solution=sol, ramp=rr)


def _capped(solver, max_steps):
    """``solver`` with its step cap lowered to ``max_steps`` (None: as it is)."""
    if max_steps is None or max_steps >= solver.max_steps:
        return solver
    return dataclasses.replace(solver, max_steps=int(max_steps))


#: fractions of ``he_pressure`` at which `swing_shut` tries to swing the valve shut, in turn
SWING_FRACTIONS = (1.0, 1.0 / 3.0, 1.0 / 9.0)


def swing_shut(valve, scene: Scene, x, *, material=None, ref=None, say=_quiet,
               fractions=SWING_FRACTIONS):
    """The barrier path's start: the valve swung shut by FIRE on the smooth penalty law (to
    a relative residual of at most 1e-4) at ``scene.he_pressure`` times each of
    ``fractions`` in turn, the first closure that converges to a state with no crossing
    and every barrier distance positive; else ``x`` (the placement).  Projected Newton
    from the open valve meets the fold limit of its line search at once on soft leaflets
    (Table 4: no progress in 500 iterations), while FIRE's dynamics swing them shut; from
    FIRE's state, Newton re-settles the valve on the barrier in a few steps (and ramps up
    to ``he_pressure`` from a lighter swing).  The lighter loads are for leaflets too soft
    to swing shut cleanly at ``he_pressure`` (Table 5's Gent valve, E = 0.1 MPa: FIRE
    stagnates at 3 mmHg, residual 0.77, with leaflets crossing, and converges at 1 mmHg
    to a separated state).  The final states are equilibria of the barrier law either
    way.  ref: a mapped reference (`valve.close`).  Returns (state, the pressure of
    its smooth-law equilibrium, mmHg; 0 for the placement), from which the first barrier
    closure continues where it lies below that closure's load."""
    material = scene.material() if material is None else material
    for f in fractions:
        p = scene.he_pressure * f
        say(f"swinging shut at {p:.3g} mmHg (fire solver, smooth contact), the start of the "
            "barrier closures")
        t0 = time.perf_counter()
        sol = _smooth_fire(valve, scene, material, p, x, ref, check_state=True)
        y = np.asarray(sol.x, np.float64)
        ok = sol.converged and separated(valve, y)
        say(f"  {sol.describe()}; {time.perf_counter() - t0:.2f} s"
            + ("" if ok else "; not a separated start"))
        if ok:
            return y.astype(np.asarray(x).dtype), float(p)
    y = watched_swing(valve, scene, x, material=material, ref=ref, say=say)
    if y is not None:
        return y.astype(np.asarray(x).dtype), 0.0
    say("  the barrier closures start from the placement")
    return x, 0.0


#: FIRE steps between two separation checks of `watched_swing`.
WATCH_STEPS = 200


def watched_swing(valve, scene: Scene, x, *, material=None, ref=None, say=_quiet,
                  every: int = WATCH_STEPS):
    """The last separated state (`separated`) of a FIRE swing on the smooth penalty law
    at ``scene.he_pressure`` from x, checked every ``every`` steps (each round a FIRE run
    of that many steps from the state of the one before, up to ``scene.max_steps`` in
    all); None where the first round already ends unseparated.  No equilibrium: the
    start that `swing_shut` falls back on where no swing converges to a separated state,
    before the placement.  FIRE swings leaflets shut where projected Newton from the
    open valve stalls, and the last separated state of a swing that then crosses or
    stagnates is most of the way there: the default StVK valve at h = 3 mm, whose swings
    at 3, 1 and 1/3 mmHg end unseparated, closes from its state after 300 FIRE steps in
    43 + 38 Newton steps, and stalls from the placement at 1.6 mmHg after 2104."""
    if not (isinstance(every, int) and every > 0):
        raise ValueError(f"every must be a positive integer; got {every!r}")
    material = scene.material() if material is None else material
    every = min(every, scene.max_steps)
    p = scene.he_pressure
    say(f"swinging shut at {p:.3g} mmHg (fire solver, smooth contact), checked every "
        f"{every} steps, the start of the barrier closures")
    t0, best, steps = time.perf_counter(), None, 0
    y = np.asarray(x)
    while steps < scene.max_steps:
        sol = _smooth_fire(valve, scene, material, p, y, ref, max_steps=every)
        y = np.asarray(sol.x, np.float64)
        steps += int(sol.stats.steps)
        if not separated(valve, y):
            break
        best = (y, steps)
        if sol.converged or int(sol.stats.steps) < every:
            break                   # an equilibrium, or FIRE stopped on its own
    if best is None:
        say(f"  not separated after {steps} steps; {time.perf_counter() - t0:.2f} s")
        return None
    say(f"  the state after {best[1]} steps is the last separated one ({steps} steps run); "
        f"{time.perf_counter() - t0:.2f} s")
    return best[0]


def _smooth_fire(valve, scene, material, p, x, ref, *, check_state=False, max_steps=None):
    """One FIRE solve on the smooth penalty law at p mmHg from x (to a relative residual
    of at most 1e-4; ``max_steps`` default the scene's): the swings of the barrier path."""
    start = scene.replace(contact="smooth", solver="fire", rtol=max(scene.rtol, 1e-4),
                          max_steps=scene.max_steps if max_steps is None else max_steps)
    return V.close(valve, material, p, solver=start.make_solver(),
                   contact=start.contact_law(), thickness=scene.thickness,
                   fibre_angle=np.deg2rad(scene.fibre_angle), bending=scene.bending_law(),
                   x0=x, throw=False, check_state=check_state, ref=ref)


def _timed_swing(valve, scene, x, material, say, fractions=SWING_FRACTIONS):
    """`swing_shut`, and the seconds it took after compilation: (state, pressure, s)."""
    with compile_timer() as ct:
        t0 = time.perf_counter()
        x, p = swing_shut(valve, scene, x, material=material, say=say, fractions=fractions)
        return x, p, max(time.perf_counter() - t0 - ct.seconds, 0.0)


def _skipped(prev: LoadSolve, p, why, say) -> LoadSolve:
    say(f"closing at {p:g} mmHg: skipped, {why}")
    rep = dataclasses.replace(prev.report, pressure=float(p), steps=0, wall_s=0.0,
                              compile_s=0.0)
    return dataclasses.replace(prev, report=rep, start_s=0.0)


def _in_turn(valve, scene, material, x, pressures, nbrs, first, done, swung, say,
             stop=False, p0=0.0, hint=None):
    """The loads of `close_valve` on the scene's own path (no fallback).  stop: end
    after the first load that failed other than at a limit point (the fallback closes
    every load again).  hint: `close_load`'s, for every load."""
    start_s = 0.0
    if scene.contact == "barrier" and not swung and not done:
        x, p0, start_s = _timed_swing(valve, scene, x, material, say)
    out, p_prev = list(done), p0
    if done:
        x, p_prev = np.asarray(done[-1].solution.x), float(done[-1].report.state_pressure)
    for i, p in enumerate(pressures):
        if i < len(done):
            continue
        prev = out[-1] if out else None
        if prev is not None and prev.limit_point:
            out.append(_skipped(prev, p, "above the limit point", say))
            continue
        if prev is not None and not np.all(np.isfinite(prev.x)):
            out.append(_skipped(prev, p, "the state before it is not finite", say))
            continue
        f = first[i] if i < len(first) else None
        if prev is not None and len(prev.ramp.history) > 1:
            f = None          # the batched attempt started from another state
        # the ramp continues from the start's pressure where it lies below the load; a
        # start at or above it (the barrier path's own swing-shut at the load itself, a
        # smooth-law state; equal loads) is ramped as from the placement, from 0
        ls = close_load(valve, scene, p, x, p_from=p_prev if p_prev < p else 0.0,
                        material=material, nbrs=nbrs,
                        first=f, hint=hint, say=say)
        if i == 0 and start_s:
            ls = dataclasses.replace(ls, start_s=start_s)
        out.append(ls)
        if stop and not ls.converged and not ls.limit_point:
            break
        x, p_prev = np.asarray(ls.solution.x), float(ls.report.state_pressure)
    return tuple(out)


def _may_fall_back(scene: Scene) -> bool:
    """The scene's closures fall back on the barrier path where they fail: its
    ``fallback`` is on, its law the smooth penalty, its precision float64 (the barrier
    path's)."""
    return bool(scene.fallback and scene.contact == "smooth"
                and scene.precision == "float64")


def fallback_scene(scene: Scene) -> Scene | None:
    """The scene of the barrier path (projected Newton on the barrier law) that a failed
    closure of ``scene`` falls back on, or None where ``scene`` has no fallback
    (`_may_fall_back`).  Used by `fall_back` and by the optimiser, which falls back for a
    whole run."""
    return scene.replace(contact="barrier", solver="newton") if _may_fall_back(scene) \
        else None


def _falls_back(scene: Scene, loads) -> LoadSolve | None:
    """The first load that failed in a way the barrier path may mend, where ``scene``
    allows a fallback (`close_valve`), else None."""
    if not _may_fall_back(scene):
        return None
    for ls in loads:
        if ls.limit_point:         # the membrane's inflation limit: no law mends it
            return None
        if not ls.converged:
            return ls
    return None


def separated(valve, x) -> bool:
    """x is a start the barrier closures can move from: it passes the state check
    (`V.state_failure`: finite, no collapsed triangle and no edge past the fold limit,
    which the barrier solver's steps keep, no leaflets crossing and no leaflet through
    itself: the barrier's pairs see distances, not an edge that already passes through a
    face, so a crossing at the start would stay), and every barrier pair is apart."""
    from ..contact.ipc_pairs import build_pairs
    x = np.asarray(x, np.float64)
    return bool(V.state_failure(valve, x) is None
                and build_pairs(valve.barrier_topology, x, 1.0).min_distance > 0)


def fall_back(valve, scene: Scene, loads, failed: LoadSolve, *, material=None, x0=None,
              pressures, say=_quiet) -> tuple:
    """The valve closed again on the barrier law (projected Newton), every load, after
    ``failed`` (a `LoadSolve` of ``loads``, the scene's own attempt) did not converge.
    The barrier closures start from the first load's state of ``loads`` where it is
    separated (`separated`: the smooth law's closure, converged or not, is the swing
    shut that the barrier path needs), else from x0 (default the placement; the
    placement too where x0 is no separated start, e.g. leaflets pushed through one
    another) swung shut under the lighter loads of `swing_shut` (its first,
    ``he_pressure``, is the smooth closure that failed).  A load after one that the
    barrier path did not close is skipped (reported with the state before it, 0 steps).
    Each report names the failure (``fallback``) and includes the failed attempt's time."""
    why = f"{path_name(scene)} failed at {failed.report.pressure:g} mmHg: " \
          f"{failed.report.describe()}"
    say(f"fallback: {why}; closing again on the barrier law (newton solver)")
    barrier = fallback_scene(scene)
    start, swing_s, p_swung = np.asarray(loads[0].x, np.float64), 0.0, 0.0
    if separated(valve, start):
        x = start
        say(f"  the barrier closures start from the {path_name(scene)} state at "
            f"{loads[0].report.pressure:g} mmHg")
    else:
        x = np.asarray(valve.x_start if x0 is None else x0, np.float64)
        say(f"  the {path_name(scene)} state at {loads[0].report.pressure:g} mmHg is no "
            "separated start (crossing, touching or folded): the barrier closures start "
            "from a swing-shut under a lighter load")
        if x0 is not None and not separated(valve, x):
            # a swing from a start whose leaflets cross ends crossed (FIRE on the penalty
            # law settles the crossed sheets), and the barrier cannot start there
            say("  the given start is no separated start either: the swing starts from "
                "the placement")
            x = np.asarray(valve.x_start, np.float64)
        x, p_swung, swing_s = _timed_swing(valve, barrier, x, material, say,
                                           SWING_FRACTIONS[1:])
    # a load after one that failed starts from no equilibrium: it is skipped (a Gent
    # valve of Table 5 at 0.1 MPa spent 142 s on an 80 mmHg closure from the state of a
    # failed 3 mmHg one, to fail again)
    # where the failed path ran away, the barrier ramps try that pressure right after
    # their own first runaway instead of halving down to it (`continuation.ramp`'s hint):
    # the stress suite's soft neo-Hookean valve (template (a), 0.05 MPa) ran away on
    # FIRE at 12.6 mmHg, and the barrier ramp from 80 mmHg spent two runaways (41.5 and
    # 22.2 mmHg, 140 Newton steps) to learn the same
    escapes = [ls.ramp.p_escape for ls in loads if ls.ramp.p_escape is not None]
    out = _in_turn(valve, barrier, material, x, pressures, None, (), (), True, say,
                   stop=True, p0=p_swung, hint=min(escapes) if escapes else None)
    while len(out) < len(pressures):
        out += (_skipped(out[-1], pressures[len(out)], f"the closure at "
                         f"{out[-1].report.pressure:g} mmHg did not converge", say),)
    merged = []
    for i, mine in enumerate(out):
        rep, start_s = dataclasses.replace(mine.report, fallback=why), mine.start_s
        if i < len(loads):          # the failed attempt's time counts
            theirs = loads[i]
            rep = dataclasses.replace(rep, wall_s=rep.wall_s + theirs.report.wall_s,
                                      compile_s=rep.compile_s + theirs.report.compile_s)
            start_s += theirs.start_s
        if i == 0:
            start_s += swing_s
        merged.append(dataclasses.replace(mine, report=rep, start_s=start_s))
    return tuple(merged)


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


def close_valve(valve, scene: Scene, *, material=None, x0=None, pressures=None, nbrs=None,
                first=(), done=(), throw: bool = False,
                say: Callable[[str], None] = _quiet) -> tuple:
    """The valve closed under ``pressures`` mmHg in turn (default the scene's
    (he_pressure, pressure)), each load from the state of the one before (`close_load`;
    the first from x0, default ``valve.x_start``, settled first where it passes the
    material's stretch limit (`admissible_start`), swung shut first on the barrier path),
    with the barrier path as the fallback where the scene's fails (module docstring).
    Returns one `LoadSolve` a load.

    first: per load, a first attempt already solved (`close_load`); the attempt at a
    later load is used only where the load before ended with its own first attempt (the
    batched program solved from that state).  done: the first loads' `LoadSolve`s, already
    closed by this driver on the scene's path (the stress suite's shared 3 mmHg closure),
    taken as they are.  throw: raise `ConvergenceError` at the first load that did not
    converge (its ``solution`` is the `ValveSolution`)."""
    pressures = ((scene.he_pressure, scene.pressure) if pressures is None
                 else tuple(float(p) for p in pressures))
    material = scene.material() if material is None else material
    x = np.asarray(valve.x_start if x0 is None else x0, scene.dtype)
    if not done:
        y = admissible_start(valve, scene, x, material=material, say=say)
        if y is not x:          # the batched first attempts started past the limit
            x, x0, first = y, y, ()
    out = _in_turn(valve, scene, material, x, pressures, nbrs, first, tuple(done), False,
                   say, stop=_may_fall_back(scene))
    failed = _falls_back(scene, out)
    if failed is not None:
        out = fall_back(valve, scene, out, failed, material=material, x0=x0,
                        pressures=pressures, say=say)
    if throw:
        for ls, p in zip(out, pressures):
            if not ls.converged:
                raise ConvergenceError(f"valve closure at {p:g} mmHg did not converge: "
                                       f"{ls.report.describe()}", ls.solution)
    return out
