"""The stress suite's harness (a benchmark, not part of the library): run closures over a
matrix of materials, loads, templates, models and precisions, plus hard cases, and
classify every run.

Each run ends one of three ways (`classify`):

* ``converged``: the solve at the run's load reports success with a finite relative
  residual below rtol, the state is finite, no triangle is collapsed or folded over
  (`jaxvalve.valve.checks`), no two leaflets cross (`jaxvalve.valve.leaflet_crossings`, an exact
  test that shares no code with contact), a Gent state keeps every triangle inside its
  stretch limit (checked here in NumPy), and every coaptation metric is finite;
* ``reported``: the solve says it did not converge (its result name and residual are the
  cause), or a clear jaxvalve error was raised (`JaxvalveError`, `ConvergenceError`);
* ``silent``: silently wrong, which must never happen: a claimed convergence that fails a
  check, a non-finite residual, state or metric returned as a result, or an unexpected
  exception type (IndexError, FloatingPointError, ...).

A run at load P is a two-stage continuation like `jaxvalve.simulate`, by the same closure
driver (`jaxvalve.valve.closure`): the valve is closed at 3 mmHg from the placement, then at P
from that state, with continuation in pressure where a solve runs away (for P = 3 the
first stage is the run).  The 3 mmHg stage is shared by the runs at 80 and 200 mmHg of one material, so a
group of (E, P) costs one closure per load.  The run is judged on its final state, the one
it returns; the 3 mmHg stage's result is recorded with it (``stage1``).

The paper's Fig. 3 templates (a) r=11, a=11, b=11; (b) r=12, a=13, b=13; (c) r=13, a=13,
b=14 mm, alpha = 160 degrees, break the template's rule 2b > |AD| (docs/benchmark-notes.md).  The
suite tries each as given (a `ParameterError` naming b is the expected, clear report) and
runs the matrix on the nearest valid variant: the same r and a, with b = |AD|/2 + 1 mm
(`paper_templates`).  The root is the benchmark root fitted to each template's sutured
length.

`benchmarks/stress.py` runs the full matrix and prints the pass table; `tests/stress/`
runs a small part (`tests/conftest.py` loads this file as the module ``stress_suite``).
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
import traceback

import numpy as np

from jaxvalve import valve as V
from jaxvalve.valve.checks import FOLD_DEG, crossing_depth, gent_invariant, triangle_checks
from jaxvalve.errors import ConvergenceError, JaxvalveError
from jaxvalve.geometry.leaflet_mesh import LeafletMesh, mesh_leaflet
from jaxvalve.geometry.mesh import signed_areas_np, triangle_angles
from jaxvalve.scene import MODELS, PRECISIONS, Scene
from jaxvalve.valve.closure import close_valve
from jaxvalve.geometry.template import PAPER_TEMPLATES, Template

__all__ = ["RunRecord", "MATRIX_E", "MATRIX_P", "STRESS_H", "STRESS_MAX_STEPS",
           "paper_templates", "make_valve", "mapped_mesh", "closed_state", "perturbed_mesh",
           "poor_mesh", "penetrated_start",
           "run_group", "run_penetration", "classify", "summarise", "pass_rate",
           "limit_analysis", "read_csv", "BULGE_RADIUS_MM", "OUTCOMES"]

MATRIX_E = (0.05, 0.1, 1.0, 10.0, 20.0)      # MPa
MATRIX_P = (3.0, 80.0, 200.0)                # mmHg
STRESS_H = 2.0                               # mm (h = 3 mm does not converge; docs/known-limits.md)
STRESS_MAX_STEPS = 4000                      # FIRE steps a solve
HE_PRESSURE = 3.0
#: the bulge radii (mm, reference) that can explain a limit point (`limit_analysis`): at
#: least a millimetre (a few elements of the stress mesh), at most the root's annulus
#: radius (12 mm): a leaflet's belly cannot balloon as a sphere larger than the root
BULGE_RADIUS_MM = (1.0, 12.0)
OUTCOMES = ("converged", "reported", "silent")
#: results of `valve.close(..., check_state=True)`: the solver met the tolerance, the
#: state check failed (without the check these runs would be silently wrong)
GUARD_RESULTS = ("leaflets_cross", "inverted_triangles")


# ----------------------------------------------------------------------------- inputs
def paper_templates(margin: float = 1.0) -> dict:
    """{'a'|'b'|'c': (valid Template, the paper's parameters dict)}: the paper's Fig. 3
    templates with b raised to |AD|/2 + margin mm (r, a, alpha = 160 degrees kept)."""
    out = {}
    for key, kw in PAPER_TEMPLATES.items():
        chord = 2 * (kw["r"] * math.sin(math.radians(80)) + kw["a"] * math.cos(math.radians(80)))
        b = max(kw["b"], round(chord / 2 + margin, 2))
        out[key] = (Template(r=kw["r"], a=kw["a"], b=b, alpha=160.0), dict(kw, alpha=160.0))
    return out


def make_valve(template: Template, h: float = STRESS_H, mesh: LeafletMesh | None = None):
    """The valve of ``template`` at mesh size h in the benchmark root fitted to it (or of
    a given, e.g. perturbed or mapped, ``mesh`` of that template)."""
    from jaxvalve.geometry.root import benchmark_root
    lmesh = mesh_leaflet(template, h) if mesh is None else mesh
    return V.build_valve(benchmark_root(template.sutured_length, wall=False), lmesh)


def mapped_mesh(base: LeafletMesh, template: Template) -> LeafletMesh:
    """``base``'s triangles with its nodes moved onto ``template``
    (`jaxvalve.geometry.template_map`): every template then has the same topology, so one compiled
    solve per (model, precision) serves them all (a compile costs 15-30 s here)."""
    from jaxvalve.geometry.template_map import template_map
    if template == base.template:
        return base
    tm = template_map(base)
    th = (template.r, template.a, template.b, template.alpha)
    pts = np.asarray(tm.points(*th), float)
    return dataclasses.replace(base, template=template, points=pts,
                               sutured_t=np.asarray(tm.sutured_t(template.r, template.a,
                                                                 template.alpha), float))


def _interior(lmesh: LeafletMesh):
    """Indices of interior template nodes (the mesher puts the boundary nodes first)."""
    from jaxvalve.geometry.mesh import boundary_nodes
    return np.flatnonzero(~boundary_nodes(lmesh.triangles))


def min_angles(points, triangles) -> np.ndarray:
    """Smallest angle (degrees) of each triangle (M,)."""
    return triangle_angles(points, triangles).min(axis=1)


def perturbed_mesh(lmesh: LeafletMesh, fraction: float = 0.3, seed: int = 0) -> LeafletMesh:
    """The mesh with each interior node moved by a random vector of length up to
    ``fraction * h`` (seeded); a node whose move would invert a triangle moves half as
    far, until none does.  Boundary nodes stay (they carry the sutured and free edges)."""
    rng = np.random.default_rng(seed)
    p0 = np.asarray(lmesh.points, float)
    tri = np.asarray(lmesh.triangles)
    inner = _interior(lmesh)
    r = fraction * lmesh.h * np.sqrt(rng.uniform(size=len(inner)))
    th = rng.uniform(0, 2 * np.pi, size=len(inner))
    d = np.zeros_like(p0)
    d[inner] = np.column_stack([r * np.cos(th), r * np.sin(th)])
    for _ in range(30):
        p = p0 + d
        bad = signed_areas_np(p, tri) <= 0.05 * signed_areas_np(p0, tri)
        if not bad.any():
            return dataclasses.replace(lmesh, points=p)
        d[np.unique(tri[bad])] *= 0.5
    raise RuntimeError("perturbed_mesh: could not keep the triangles oriented")  # pragma: no cover


def poor_mesh(lmesh: LeafletMesh, n_bad: int = 4, target_deg: float = 3.0,
              seed: int = 1) -> LeafletMesh:
    """The mesh with ``n_bad`` interior nodes dragged toward the opposite edge of one of
    their triangles, until that triangle's smallest angle is about ``target_deg`` (sliver
    triangles; every triangle stays counter-clockwise)."""
    rng = np.random.default_rng(seed)
    p = np.asarray(lmesh.points, float).copy()
    tri = np.asarray(lmesh.triangles)
    inner = _interior(lmesh)
    moved, used = 0, set()
    for v in rng.permutation(inner):
        if moved == n_bad:
            break
        star = np.flatnonzero(np.any(tri == v, axis=1))
        if used & set(tri[star].ravel().tolist()):
            continue                                   # keep the slivers apart
        t = tri[star[0]]
        a, b = [w for w in t if w != v]
        m = 0.5 * (p[a] + p[b])
        for s in np.linspace(0.5, 0.01, 50):
            q = p.copy()
            q[v] = m + s * (p[v] - m)
            if np.any(signed_areas_np(q, tri[star]) <= 0):
                break
            if min_angles(q, tri[star[:1]])[0] <= target_deg:
                p = q
                moved += 1
                used |= set(tri[star].ravel().tolist())
                break
    return dataclasses.replace(lmesh, points=p)


def penetrated_start(valve, x, depth: float = 1.5):
    """x (N, 3) with each leaflet's free nodes pushed ``depth`` mm (at the free edge; less
    toward the sutured edge, by their template distance to it) toward and past the axis:
    neighbouring leaflets then cross their shared mid-plane by ~1.7 depth mm in all."""
    x = np.array(x, float)
    root = valve.root
    axis = np.asarray(root.axis, float)
    origin = np.asarray(root.origin, float)
    ref = np.asarray(valve.leaflet.points, float)
    sut = ref[valve.leaflet.sutured]
    dist = np.min(np.linalg.norm(ref[:, None] - sut[None], axis=-1), axis=1)
    w = dist / dist.max()
    for i in range(3):
        sl = valve.leaflet_slice(i)
        c = x[sl].mean(axis=0) - origin
        u = c - np.dot(c, axis) * axis
        u /= np.linalg.norm(u)
        x[sl] -= depth * w[:, None] * u[None]
    return x


# ----------------------------------------------------------------------------- records
@dataclasses.dataclass
class RunRecord:
    """One run of the stress suite (units mm, MPa, mmHg)."""

    case: str
    template: str
    mesh: str
    model: str
    precision: str
    E: float
    P: float
    extra: str = ""
    start: str = "placement"
    outcome: str = ""
    cause: str = ""
    result: str = ""
    path: str = ""                   # the closure path that gave the result
    steps: int = 0
    residual: float = math.nan
    limit_pressure: float = math.nan  # mmHg: the highest equilibrium, where a limit point
    stage1: str = ""
    crossings: int = -1
    ipctk: str = ""                  # the IPC toolkit's check: clean, intersects, not run
    cross_depth: float = 0.0         # `checks.crossing_depth` of the crossing pairs (mm)
    min_J: float = math.nan
    max_fold_deg: float = math.nan
    max_stretch: float = math.nan
    min_stretch: float = math.nan    # smallest principal stretch over triangles
    gent_ratio: float = math.nan     # max (I1 + 1/I2 - 3) / Jm over triangles (Gent)
    h_E: float = math.nan
    h_CC: float = math.nan
    NCCA_pct: float = math.nan
    wall_s: float = 0.0

    def as_row(self) -> dict:
        return dataclasses.asdict(self)


def ipctk_intersects(valve, x) -> bool | None:
    """The independent intersection check of a closed valve: the IPC toolkit's
    `has_intersections` (ipctk, a C++ implementation of its own, a test dependency) on
    the leaflets' triangles of x (N, 3) mm, the commissure rings left out (neighbouring
    leaflets are sewn to one commissure point, so the elements that hold it touch by
    construction).  None where ipctk is not installed."""
    try:
        import ipctk
    except ImportError:
        return None
    tri = valve.triangles
    keep = np.asarray(valve.contact_topology.tri_pin) < 0          # commissure rings
    t = tri[keep]
    used, inv = np.unique(t, return_inverse=True)
    t = inv.reshape(t.shape).astype(np.int32)
    v = np.asarray(x, float)[used]
    return bool(ipctk.has_intersections(ipctk.CollisionMesh(v, ipctk.edges(t), t), v))


def _metric_values(m):
    vals = [m.h, m.h_cc, m.h_c, m.h_e, m.ncca_valve, m.h_avr_valve]
    arrays = [m.area, m.zone_area, m.ncca, m.h_avr, m.free_edge_length, m.central_point]
    return np.concatenate([np.asarray(vals, float)] + [np.ravel(np.asarray(a, float))
                                                       for a in arrays])


def _judge(rec: RunRecord, valve, ls, scene: Scene):
    """Fill the checks of ``rec`` from the closure's outcome at its load (a
    `jaxvalve.valve.closure.LoadSolve`: its state, report and continuation) and classify it.
    A closure that ended at a limit point is reported as ``limit_point``, its state the
    equilibrium at the highest pressure found."""
    from jaxvalve.simulation import measure
    sol, x64, rep = ls.solution, ls.x, ls.report
    rec.result = rep.result
    rec.path = rep.path or ""
    rec.residual = float(rep.residual)
    rec.steps += int(rep.steps)
    finite = bool(np.all(np.isfinite(x64)))
    notes = []
    if finite:
        # a crease of the barrier law is held below 180 degrees by the hinges' fold
        # barrier; ipctk (which checks each leaflet against itself too) is the check that
        # no leaflet has folded through itself
        tc = triangle_checks(valve.ref, valve.triangles, x64, fold_deg=180.0)
        rec.min_J, rec.max_fold_deg, rec.max_stretch = tc.min_J, tc.max_fold_deg, tc.max_stretch
        rec.min_stretch = tc.min_stretch
        if not tc.ok:
            notes.append(tc.describe())
        pairs = V.leaflet_crossings(valve, x64)
        rec.crossings = int(len(pairs))
        hit = ipctk_intersects(valve, x64)
        rec.ipctk = {None: "not run", True: "intersects", False: "clean"}[hit]
        if hit and not rec.crossings:
            notes.append("ipctk finds intersecting triangles that the exact test missed")
        if rec.crossings:
            rec.cross_depth = crossing_depth(x64, valve.triangles, pairs)
            notes.append(f"{rec.crossings} crossing triangle pairs, "
                         f"{rec.cross_depth:.2f} mm deep")
        if scene.model == "gent":
            inv = gent_invariant(valve.ref, valve.triangles, x64)
            rec.gent_ratio = float(np.max(inv) / scene.Jm)
            if not rec.gent_ratio < 1.0:
                notes.append(f"Gent stretch limit passed (max (I1+1/I2-3)/Jm = "
                             f"{rec.gent_ratio:.3g})")
        try:
            m = measure(valve, x64, scene.g_c)
            rec.h_E, rec.h_CC, rec.NCCA_pct = float(m.h_e), float(m.h_cc), 100 * float(m.ncca_valve)
            if not np.all(np.isfinite(_metric_values(m))):
                notes.append("non-finite coaptation metric")
        except JaxvalveError as e:
            notes.append(f"metrics: {type(e).__name__}: {e}")
    if ls.limit_point:          # the state: the converged equilibrium at the limit pressure
        rec.limit_pressure = float(rep.limit_pressure)
        rec.outcome = "reported"
        rec.cause = ls.ramp.describe() + (" [state: " + "; ".join(notes) + "]"
                                          if notes else "")
    elif sol.converged and ls.converged:
        if not (math.isfinite(rec.residual) and rec.residual < scene.rtol):
            notes.append(f"claimed convergence at relative residual {rec.residual:.3g}")
        if not finite:
            notes.append("claimed convergence with non-finite positions")
        rec.outcome = "silent" if notes else "converged"
        rec.cause = "; ".join(notes)
    elif not finite:
        # `simulate` raises ConvergenceError here: a clear report, but the result must say so
        rec.outcome = "reported" if rec.result == "nonfinite" else "silent"
        rec.cause = (f"{rec.result} (non-finite positions; simulate raises ConvergenceError)"
                     if rec.outcome == "reported" else
                     f"non-finite positions returned with result {rec.result}")
    else:
        rec.outcome = "reported"
        rec.cause = f"{rec.result} at relative residual {rec.residual:.2e}"
        if rep.cause:
            rec.cause += f" ({rep.cause})"
        if notes:
            rec.cause += " [state: " + "; ".join(notes) + "]"
    if len(ls.ramp.history) > 1:       # the continuation's solves, in order
        rec.cause += " [continuation: " + ", ".join(
            f"{q:.3g} mmHg {r}" for q, r, _, _ in ls.ramp.history) + "]"
    return rec


def classify(rec: RunRecord) -> str:
    """The run's outcome, one of OUTCOMES (set by the runners)."""
    return rec.outcome


def _exception(rec: RunRecord, e: BaseException) -> RunRecord:
    clear = isinstance(e, (JaxvalveError, ConvergenceError))
    rec.outcome = "reported" if clear else "silent"
    rec.result = type(e).__name__
    msg = str(e).splitlines()[0] if str(e) else ""
    rec.cause = f"{type(e).__name__}: {msg}"
    if not clear:
        rec.cause += " | " + traceback.format_exc(limit=3).replace("\n", " ")[-400:]
    return rec


def _first_stage(valve, scene: Scene):
    """The closure at `HE_PRESSURE` from the valve's start, as `simulate` runs it (the
    one closure driver, `jaxvalve.valve.closure.close_valve`): a `LoadSolve`."""
    return close_valve(valve, scene, pressures=(HE_PRESSURE,))[0]


def _next_stage(valve, scene: Scene, p, first):
    """The closure at p > `HE_PRESSURE` after the first stage (its `LoadSolve`), as
    `simulate` runs it (`jaxvalve.valve.closure.close_valve` with the first stage done): from
    the first stage's state, with continuation in pressure where a solve runs away
    (``escaped``: a node farther from its start than the valve's diameter, soft leaflets
    ballooning out of the root), so that a load past the membrane's inflation limit ends
    as ``limit_point``."""
    return close_valve(valve, scene, pressures=(HE_PRESSURE, p), done=(first,))[1]


def run_group(valve, *, template: str, mesh: str, model: str, precision: str,
              Es=MATRIX_E, Ps=MATRIX_P, rtol: float = 1e-4,
              max_steps: int = STRESS_MAX_STEPS, case: str = "matrix", extra: dict | None = None,
              on_record=None) -> list:
    """Runs for every (E, P) of one (valve, model, precision): per E, close at 3 mmHg from
    the placement, then at each P > 3 from that state.  ``extra``: more `Scene` fields
    (Jm, E1, E2, E3, ...), applied to every run.  Returns the `RunRecord`s."""
    extra = dict(extra or {})
    tag = " ".join(f"{k}={v}" if isinstance(v, (bool, str)) else f"{k}={v:g}"
                   for k, v in extra.items())
    tpl = valve.leaflet.template
    out = []
    for E in Es:
        def new(P):
            return RunRecord(case=case, template=template, mesh=mesh, model=model,
                             precision=precision, E=float(E), P=float(P), extra=tag)
        pending = [new(P) for P in Ps]
        t0 = time.perf_counter()
        try:
            scene = Scene(r=tpl.r, a=tpl.a, b=tpl.b, alpha=tpl.alpha, h=valve.leaflet.h,
                          model=model, E=float(E), precision=precision, rtol=rtol,
                          max_steps=max_steps, pressure=float(max(Ps)),
                          he_pressure=HE_PRESSURE, **extra)
            st1 = _first_stage(valve, scene)
        except Exception as e:  # noqa: BLE001 - classified, not swallowed
            for rec in pending:
                rec.wall_s = time.perf_counter() - t0
                out.append(_exception(rec, e))
                _emit(on_record, rec)
            continue
        stage1 = f"{st1.report.result} {st1.report.residual:.1e}"
        w1 = time.perf_counter() - t0
        for rec in pending:
            t1 = time.perf_counter()
            rec.stage1 = stage1
            try:
                if rec.P == HE_PRESSURE:
                    _judge(rec, valve, st1, scene)
                elif not np.all(np.isfinite(st1.x)):
                    raise ConvergenceError(f"valve closure at {HE_PRESSURE:g} mmHg produced "
                                           "non-finite positions", st1.solution)
                else:
                    rec.steps = st1.report.steps
                    _judge(rec, valve, _next_stage(valve, scene, rec.P, st1), scene)
            except Exception as e:  # noqa: BLE001
                _exception(rec, e)
            # the shared 3 mmHg stage (compile included) is timed in the group's first run
            rec.wall_s = (w1 if rec is pending[0] else 0.0) + time.perf_counter() - t1
            out.append(rec)
            _emit(on_record, rec)
    return out


def closed_state(valve, *, model: str = "stvk", precision: str = "float64", E: float = 1.0,
                 P: float = 80.0, rtol: float = 1e-4, max_steps: int = STRESS_MAX_STEPS):
    """The valve closed at 3 mmHg and then at P (float64 positions), or None when that
    fails (`run_penetration` then closes it itself and reports the failure)."""
    tpl = valve.leaflet.template
    try:
        scene = Scene(r=tpl.r, a=tpl.a, b=tpl.b, alpha=tpl.alpha, h=valve.leaflet.h,
                      model=model, E=float(E), precision=precision, rtol=rtol,
                      max_steps=max_steps, pressure=float(P))
        x = _next_stage(valve, scene, P, _first_stage(valve, scene)).x
    except Exception:  # noqa: BLE001 - run_penetration then closes it itself and reports
        return None
    return x if np.all(np.isfinite(x)) else None


def run_penetration(valve, *, template: str, model: str = "stvk", precision: str = "float64",
                    E: float = 1.0, P: float = 80.0, depth: float = 1.5, rtol: float = 1e-4,
                    max_steps: int = STRESS_MAX_STEPS, x_closed=None, on_record=None):
    """A closure at P from a start whose leaflets are pushed through one another
    (`penetrated_start` of the closed state at P, ``x_closed``, or of a closure at P from
    the placement).  Returns the `RunRecord` (start names the crossing pairs at the start)."""
    tpl = valve.leaflet.template
    rec = RunRecord(case="penetration", template=template, mesh="regular", model=model,
                    precision=precision, E=float(E), P=float(P), extra=f"depth={depth:g}")
    t0 = time.perf_counter()
    try:
        scene = Scene(r=tpl.r, a=tpl.a, b=tpl.b, alpha=tpl.alpha, h=valve.leaflet.h,
                      model=model, E=float(E), precision=precision, rtol=rtol,
                      max_steps=max_steps, pressure=float(P))
        if x_closed is None:
            s2 = _next_stage(valve, scene, P, _first_stage(valve, scene))
            x_closed = s2.x
            rec.stage1 = f"{s2.report.result} {s2.report.residual:.1e}"
        x0 = penetrated_start(valve, x_closed, depth)
        n0 = len(V.leaflet_crossings(valve, x0))
        rec.start = f"penetrated ({n0} crossing pairs)"
        # the barrier closes leaflets that are apart: the driver refuses a crossed start
        # with a ParameterError naming it (reported, never a crossed state as converged)
        _judge(rec, valve, close_valve(valve, scene, x0=x0.astype(scene.dtype),
                                       pressures=(P,))[0], scene)
    except Exception as e:  # noqa: BLE001
        _exception(rec, e)
    rec.wall_s = time.perf_counter() - t0
    _emit(on_record, rec)
    return rec


def run_invalid_templates(on_record=None) -> list:
    """The paper's Fig. 3 templates as given: each must be refused with a clear error."""
    out = []
    for key, (_, kw) in paper_templates().items():
        rec = RunRecord(case="paper-template", template=f"{key} as given", mesh="-",
                        model="-", precision="-", E=math.nan, P=math.nan)
        try:
            Scene(**kw)
            rec.outcome, rec.cause = "silent", "an invalid template was accepted"
        except Exception as e:  # noqa: BLE001
            _exception(rec, e)
        out.append(rec)
        _emit(on_record, rec)
    return out


def _emit(fn, rec):
    if fn is not None:
        fn(rec)


# ----------------------------------------------------------------------------- analysis
def _extra(tag: str) -> dict:
    """`run_group`'s ``extra`` back from its tag ("Jm=0.3", "E1=0.05 E2=0.3 E3=1.2")."""
    out = {}
    for item in tag.split():
        k, v = item.split("=", 1)
        out[k] = {"True": True, "False": False}.get(v, v)
        if isinstance(out[k], str):
            try:
                out[k] = float(v)
            except ValueError:
                pass
    return out


def limit_analysis(rec: RunRecord) -> tuple[bool, str]:
    """(predicted, text): whether the inflation analysis (`jaxvalve.mechanics.inflation`)
    explains the run's limit point.  Predicted where the run's material has an inflation
    limit and the limit pressure is that of a balloon whose reference radius lies in
    `BULGE_RADIUS_MM`; the text states the analysis (the peak's stretch and P R0, the
    implied radius, or that the material stiffens and has none).  For a material that
    stiffens under inflation but softens in compression (StVK below a principal stretch
    of 1/sqrt(3), `jaxvalve.mechanics.inflation.compression_limit`) the text says how far
    the state at the limit is compressed (``min_stretch``), but predicts nothing: converged
    states are compressed past that stretch too (template (c), StVK at 0.1 MPa and 80
    mmHg: 0.414)."""
    return _limit_analysis(rec.model, rec.E, rec.extra, rec.limit_pressure, rec.min_stretch)


@functools.lru_cache(maxsize=None)
def _limit_analysis(model, E, extra, p, min_stretch=math.nan):
    from jaxvalve.mechanics.inflation import compression_limit, inflation_limit
    if not (math.isfinite(p) and p > 0):
        return False, f"limit pressure unknown ({p}): not predicted"
    scene = Scene(model=model, E=E, **_extra(extra))
    lim = inflation_limit(scene.material(), scene.thickness)
    if not lim.exists:
        c = compression_limit(scene.material())
        if c is None:
            return False, lim.describe() + ": not predicted"
        head = (lim.describe() + f", but it softens in compression below a principal "
                f"stretch of {c:.3f}")
        if not math.isfinite(min_stretch):
            return False, head + " (the state's stretches were not recorded): not predicted"
        past = "past it" if min_stretch < c else "not past it"
        return False, (head + f"; the state at the limit is compressed to {min_stretch:.3f}, "
                       f"{past} (converged states can be too): not predicted")
    r0 = lim.radius(p)
    lo, hi = BULGE_RADIUS_MM
    ok = lo <= r0 <= hi
    return ok, lim.describe(p) + (": predicted" if ok else
                                  f": not predicted (outside {lo:g}-{hi:g} mm)")


def read_csv(path) -> list:
    """The `RunRecord`s of a CSV written by `write_csv` / `append_csv`."""
    import csv
    types = {f.name: f.type for f in dataclasses.fields(RunRecord)}
    conv = {"float": float, "int": int, "str": str}
    out = []
    with open(path, newline="") as f:
        for row in csv.DictReader(f):
            rec = RunRecord(**{k: conv[types[k]](v) for k, v in row.items() if k in types})
            if rec.result == "limit_point" and math.isnan(rec.limit_pressure):
                # files written before the field: the pressure is in the cause
                import re
                m = re.search(r"no equilibrium above ([\d.]+)", rec.cause)
                rec.limit_pressure = float(m.group(1)) if m else math.nan
            out.append(rec)
    return out


# ----------------------------------------------------------------------------- tables
def summarise(records) -> dict:
    """{(model, precision): {'tried', 'converged', 'reported', 'silent', 'guard',
    'limit'}} plus ('all', '') and ('all', precision); 'guard' counts the reported runs
    whose solver met the tolerance but whose state failed `valve.close`'s check
    (`GUARD_RESULTS`): silently wrong without it; 'limit' the runs that ended at a limit
    point the inflation analysis predicts (`limit_analysis`)."""
    table = {}
    for r in records:
        lim = r.result == "limit_point" and r.outcome == "reported" and limit_analysis(r)[0]
        keys = [(r.model, r.precision), ("all", "")]
        if r.precision in PRECISIONS:
            keys.append(("all", r.precision))
        for key in keys:
            row = table.setdefault(key, dict(tried=0, converged=0, reported=0, silent=0,
                                             guard=0, limit=0))
            row["tried"] += 1
            row[r.outcome] += 1
            row["guard"] += r.result in GUARD_RESULTS
            row["limit"] += lim
    return table


def pass_rate(records, precision: str = "float64") -> str:
    """One line: the runs of ``precision`` that converged or ended at a predicted limit
    point, of those tried (the suite's target is 95 % in float64)."""
    row = summarise(records).get(("all", precision))
    if row is None:
        return f"{precision}: no runs"
    good = row["converged"] + row["limit"]
    return (f"{precision}: converged {row['converged']} + at a predicted limit point "
            f"{row['limit']} = {good} of {row['tried']} runs ({100 * good / row['tried']:.1f} %)")


def format_table(records) -> str:
    """The pass table (per model x precision) and the list of non-converged runs."""
    t = summarise(records)
    lines = ["| model | precision | tried | converged | reported | silently wrong "
             "| of the reported: caught by the state guard | of the reported: at a "
             "predicted limit point |",
             "|---|---|---|---|---|---|---|---|"]
    keys = sorted((k for k in t if k[0] != "all"),
                  key=lambda k: (MODELS.index(k[0]) if k[0] in MODELS else 9,
                                 PRECISIONS.index(k[1]) if k[1] in PRECISIONS else 9))
    for k in keys + [("all", "")]:
        row = t[k]
        lines.append(f"| {k[0]} | {k[1]} | {row['tried']} | {row['converged']} | "
                     f"{row['reported']} | {row['silent']} | {row['guard']} | "
                     f"{row['limit']} |")
    by_case = {}
    for r in records:
        c = by_case.setdefault(r.case, dict(tried=0, converged=0, reported=0, silent=0,
                                            guard=0))
        c["tried"] += 1
        c[r.outcome] += 1
        c["guard"] += r.result in GUARD_RESULTS
    lines += ["", "| case | tried | converged | reported | silently wrong | state guard |",
              "|---|---|---|---|---|---|"]
    for k, c in by_case.items():
        lines.append(f"| {k} | {c['tried']} | {c['converged']} | {c['reported']} | "
                     f"{c['silent']} | {c['guard']} |")
    causes = {}
    for r in records:
        if r.outcome != "converged":
            causes[r.result] = causes.get(r.result, 0) + 1
    lines += ["", "Results of the runs that did not converge: "
              + ", ".join(f"{k} {v}" for k, v in sorted(causes.items(), key=lambda kv: -kv[1]))]
    lims = [r for r in records if r.result == "limit_point" and r.outcome == "reported"]
    if lims:
        lines += ["", "Limit points and the inflation analysis "
                  "(`jaxvalve.mechanics.inflation`; predicted where the material has an "
                  f"inflation limit and the bulge radius it implies lies within "
                  f"{BULGE_RADIUS_MM[0]:g}-{BULGE_RADIUS_MM[1]:g} mm; for a material "
                  "that stiffens, how far the state at the limit is compressed):", "",
                  "| template | mesh | model | E MPa | P mmHg | extra | limit mmHg | analysis |",
                  "|---|---|---|---|---|---|---|---|"]
        for r in lims:
            lines.append(f"| {r.template} | {r.mesh} | {r.model} | {r.E:g} | {r.P:g} | "
                         f"{r.extra} | {r.limit_pressure:.4g} | {limit_analysis(r)[1]} |")
    bad = [r for r in records if r.outcome != "converged"]
    if bad:
        lines += ["", "Runs that did not converge (reported) or went silently wrong:", "",
                  "| outcome | case | template | mesh | model | precision | E MPa | P mmHg "
                  "| extra | 3 mmHg stage | cause |",
                  "|---|---|---|---|---|---|---|---|---|---|---|"]
        for r in bad:
            lines.append(f"| {r.outcome} | {r.case} | {r.template} | {r.mesh} | {r.model} | "
                         f"{r.precision} | {r.E:g} | {r.P:g} | {r.extra} | {r.stage1} | "
                         f"{r.cause} |")
    return "\n".join(lines)


def write_csv(records, path):
    import csv
    rows = [r.as_row() for r in records]
    with open(path, "w", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rows[0]) if rows else ["case"])
        w.writeheader()
        w.writerows(rows)


def append_csv(rec: RunRecord, path):
    """Append one run to a CSV file (with the header when the file is new)."""
    import csv
    from pathlib import Path
    new = not Path(path).exists()
    with open(path, "a", newline="") as f:
        w = csv.DictWriter(f, fieldnames=list(rec.as_row()))
        if new:
            w.writeheader()
        w.writerow(rec.as_row())
