"""Stress suite, part 2 (issue 5): hard cases.  Gent near its stretch limit, the piecewise
mass-spring modulus (eq. 3.3), a start with the leaflets pushed through one another, and
meshes with perturbed and sliver triangles.  Each run converges with every check passed
or reports why not; never silently wrong.  Benchmark template, h = 2 mm."""
import re

import numpy as np
import pytest

import stress_suite as S
from jaxvalve import valve as V
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.scene import Scene

MAX_STEPS = 3000
H = 2.0


@pytest.fixture(scope="module")
def mesh():
    return mesh_leaflet(Scene().template(), H)


@pytest.fixture(scope="module")
def valve(mesh):
    return S.make_valve(Scene().template(), H, mesh)


def _never_silent(records):
    for r in records:
        assert r.outcome in ("converged", "reported"), (r.outcome, r.cause)


def test_gent_near_its_stretch_limit(valve):
    """Gent with a small Jm.  Jm = 0.3: the closure at 80 mmHg gets near the limit (its
    largest I1 + 1/I2 - 3 is ~0.8 Jm) and converges with every triangle inside it.
    Jm = 0.1: the placement itself already passes the limit (I1 + 1/I2 - 3 = 0.25 in its
    most stretched triangle); the driver settles it at 0 mmHg under the limit-free law
    (`closure.admissible_start`) and the closures converge from there, inside the limit."""
    recs = []
    for jm in (0.3, 0.1):
        recs += S.run_group(valve, template="benchmark", mesh="regular", model="gent",
                            precision="float64", Es=(1.0,), Ps=(3.0, 80.0),
                            max_steps=MAX_STEPS, case="gent-limit", extra=dict(Jm=jm))
    _never_silent(recs)
    assert all(r.outcome == "converged" for r in recs), [r.cause for r in recs]
    assert all(r.gent_ratio < 1.0 for r in recs)
    assert all(r.ipctk == "clean" for r in recs)
    for jm in ("Jm=0.3", "Jm=0.1"):
        assert max(r.gent_ratio for r in recs if r.extra == jm) > 0.5


def test_a_soft_table4_valve_never_crosses(valve):
    """The paper's Table 4 cell E1 = 0.18, E2 = 0.3, E3 = 1.2 MPa (mass-spring) at 80
    mmHg, on this coarse mesh: converged with every check passed, or reported with its
    cause; never crossed, by the exact test or by the IPC toolkit."""
    pytest.importorskip("ipctk")
    rec, = S.run_group(valve, template="benchmark", mesh="regular", model="mass-spring",
                       precision="float64", Es=(1.0,), Ps=(80.0,), max_steps=20_000,
                       case="table4", extra=dict(E1=0.18, E2=0.3, E3=1.2))
    _never_silent([rec])
    assert rec.path == "engine" and rec.crossings == 0 and rec.ipctk == "clean"
    if rec.outcome == "converged":
        assert rec.residual < 1e-4 and rec.max_fold_deg < 170 and rec.h_CC > 5.0
    else:
        assert rec.result in ("stagnation", "max_steps_reached"), rec.cause
        assert "residual" in rec.cause


def test_a_crossed_start_is_refused_never_claimed_closed(valve):
    """Leaflets pushed 1.5 mm through one another at the start: the barrier cannot undo a
    crossing, so the driver refuses the start with a clear error naming it (reported,
    never a crossed state as converged)."""
    x_closed = S.closed_state(valve, model="stvk", max_steps=MAX_STEPS)
    assert x_closed is not None
    x0 = S.penetrated_start(valve, x_closed, 1.5)
    assert len(V.leaflet_crossings(valve, x0)) > 0
    assert len(V.leaflet_crossings(valve, x_closed)) == 0
    rec = S.run_penetration(valve, template="benchmark", depth=1.5, x_closed=x_closed,
                            max_steps=MAX_STEPS)
    _never_silent([rec])
    assert rec.outcome == "reported" and "pairs of crossing triangles" in rec.cause


def test_perturbed_and_sliver_meshes(mesh):
    """A randomly perturbed mesh and one with four sliver triangles (smallest angle ~3
    degrees): closures at 80 mmHg converge cleanly or report."""
    pm = S.perturbed_mesh(mesh, 0.3, seed=0)
    assert np.all(pm.triangles == mesh.triangles)
    moved = np.linalg.norm(pm.points - mesh.points, axis=1)
    assert moved.max() > 0.1 * H and moved.max() <= 0.3 * H + 1e-12
    qm = S.poor_mesh(mesh, 4, 3.0, seed=1)
    ang = S.min_angles(qm.points, qm.triangles)
    assert np.sum(ang < 5.0) >= 4 and np.sum(S.min_angles(mesh.points, mesh.triangles) < 5) == 0
    tpl = Scene().template()
    recs = []
    for name, m in (("perturbed", pm), ("slivers", qm)):
        recs += S.run_group(S.make_valve(tpl, H, m), template="benchmark", mesh=name,
                            model="stvk", precision="float64", Es=(1.0,), Ps=(80.0,),
                            max_steps=MAX_STEPS, case=name)
    _never_silent(recs)


def test_a_soft_neo_hookean_valve_past_its_inflation_limit_ends_at_a_limit_point():
    """Neo-Hookean, E = 0.05 MPa (mu = E/3), paper template a at 80 mmHg: no equilibrium
    exists there (the inflation limit ~ 1.24 mu H / R is near 11 mmHg), so the closure runs
    away and the continuation in pressure brackets the limit. The run is reported as
    limit_point, never as converged, with a bracket narrower than 1 % of its upper end
    between the 3 mmHg equilibrium and the target, and the state at the limit is a clean
    closed valve (no crossing, no fold).  (`simulate` hands on the same driver's limit
    point: tests/test_closure_driver.py.)"""
    tpls = S.paper_templates()
    tpl = tpls["a"][0]
    v = S.make_valve(tpl, H, S.mapped_mesh(mesh_leaflet(tpls["b"][0], H), tpl))
    rec, = [r for r in S.run_group(v, template="a", mesh="regular", model="neo-hookean",
                                   precision="float64", Es=(0.05,), Ps=(3.0, 80.0),
                                   case="limit-point") if r.P == 80.0]
    assert rec.outcome == "reported" and rec.result == "limit_point", rec.cause
    # the limit is bracketed by the lowest runaway, or, where solves just past the fold
    # stalled before they ran away (`continuation.ramp`), by the lowest stall
    lo, stall, hi = re.search(r"no equilibrium above ([\d.]+) \((?:solves from ([\d.]+) "
                              r"stalled, )?solves at ([\d.]+)", rec.cause).groups()
    lo, hi = float(lo), float(hi)
    upper = hi if stall is None else float(stall)
    assert 3.0 < lo < upper <= hi < 80.0 and upper - lo <= 0.01 * upper
    # the inflation analysis explains it: neo-Hookean has a limit, and this one is that
    # of a bulge a few millimetres across (`stress_suite.limit_analysis`)
    assert rec.limit_pressure == pytest.approx(lo, rel=1e-3)
    ok, text = S.limit_analysis(rec)
    assert ok, text
    assert rec.crossings == 0 and rec.min_J > 0 and rec.max_fold_deg < 150
    assert "escaped" in rec.cause and "80 mmHg escaped" in rec.cause
