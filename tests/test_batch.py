"""`simulate_batch`: one valve closed under a batch of materials (the engine's FIRE phase
under vmap in one compiled program, then each member through the closure driver).

One coarse valve (h = 2 mm, StVK) is closed once as a batch of three members, once more
as another batch of three, and once per member by `simulate`, for the whole module (the
compiles dominate the time).  The `jaxvalve sweep` test reuses the batch's compiled solve.
"""
import contextlib
import csv
import io

import numpy as np
import pytest

from jaxvalve import Scene, simulate
from jaxvalve.batch import METRICS, BatchResult, simulate_batch, stack_materials
from jaxvalve.cli import main
from jaxvalve.contact import pairs as pair_lists
from jaxvalve.errors import ConvergenceError, ParameterError
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.solvers import equilibrium

SCENE = Scene(h=2.0, model="stvk")
E_FIRST = (1.0, 2.0, 3.0)
E_SECOND = (1.0, 2.0, 0.8)

PNG = b"\x89PNG\r\n\x1a\n"


def stvk(*es):
    return [StVenantKirchhoff(E=e, nu=0.45) for e in es]


@pytest.fixture(scope="module")
def runs():
    first = simulate_batch(SCENE, stvk(*E_FIRST), throw=False)
    cache = equilibrium._fire_batch._cache_size()
    second = simulate_batch(SCENE, stvk(*E_SECOND), valve=first.valve)
    seq = [simulate(SCENE.replace(E=e), valve=first.valve) for e in E_FIRST]
    return dict(first=first, second=second, seq=seq,
                cache=(cache, equilibrium._fire_batch._cache_size()))


#: how far a member's closed state (mm) and metrics (mm, %) may lie from its own
#: `simulate`'s: the batch refreshes every member's pair lists when any member needs it, so
#: a member's steps are capped at other times and its path differs within the solve's
#: tolerance (rtol = 1e-4 ends both within a few 1e-4 mm of the equilibrium)
STATE_TOL = 2e-3
METRIC_TOL = 5e-4


def test_every_member_closes_to_its_own_simulate_within_the_tolerance(runs):
    """Each member converges to the state its own `simulate` converges to, within the
    solve's tolerance, in about as many steps."""
    first, seq = runs["first"], runs["seq"]
    assert isinstance(first, BatchResult) and first.converged and len(first) == 3
    for m, s in zip(first, seq):
        assert m.parameters == {"E": s.scene.E, "nu": 0.45}
        np.testing.assert_allclose(m.x_he, s.x_he, rtol=0, atol=STATE_TOL)
        np.testing.assert_allclose(m.x, s.x, rtol=0, atol=STATE_TOL)
        for a, b in zip(m.solves, s.solves):
            assert (a.result, a.converged) == (b.result, b.converged)
            assert a.residual < SCENE.rtol and b.residual < SCENE.rtol
            assert abs(a.steps - b.steps) <= 0.1 * b.steps
        for k in METRICS:
            assert m.summary()[k] == pytest.approx(s.summary()[k], abs=METRIC_TOL), k
    # the members took different paths (so a finished member was carried along)
    assert len({m.solves[0].steps for m in first}) == 3


def test_member_result_depends_on_its_batch_only_within_the_tolerance(runs):
    """E = 1 MPa with other companions: the same closed state within the tolerance."""
    a, b = runs["first"][0], runs["second"][0]
    assert b.parameters["E"] == 1.0 and b.converged
    np.testing.assert_allclose(a.x, b.x, rtol=0, atol=STATE_TOL)
    for k in METRICS:
        assert a.summary()[k] == pytest.approx(b.summary()[k], abs=METRIC_TOL), k


def test_new_material_values_do_not_recompile(runs):
    before, after = runs["cache"]
    assert before == after
    assert runs["second"].timings["compile"] < 0.5
    assert runs["first"].timings["compile"] > 1.0


def test_unconverged_members_are_reported_with_their_residual(runs):
    """A step cap far below what the closure needs (a traced setting: no recompile): every
    member stops at it far from equilibrium (no Newton finish from there), the error names
    each member, its parameters, the load, the result and the residual, and the rows say
    so; the load after a failed one is not solved."""
    capped = SCENE.replace(max_steps=50)
    with pytest.raises(ConvergenceError) as err:
        simulate_batch(capped, stvk(1.0, 2.0), valve=runs["first"].valve)
    res, msg = err.value.solution, str(err.value)
    assert not res.converged and res.failed == [0, 1]
    he, closing = res[0].solves
    # continuation cut the load step until its step budget was spent (`Ramp.for_solver`)
    assert he.result == "max_steps_reached" and he.residual > 0.05 and he.newton_steps == 0
    assert he.steps == 10 * capped.max_steps
    assert closing.steps == 0 and not closing.converged
    assert "2 of 2 members did not converge" in msg
    assert "member 0 (stvk: E=1, nu=0.45)" in msg
    assert "3 mmHg: max_steps_reached" in msg and f"residual {he.residual:.2e}" in msg
    row = res.rows()[0]
    assert row["converged"] is False and row["residual_he"] == he.residual
    assert row["result_he"] == "max_steps_reached" and row["limit_pressure_he"] is None


def test_timings_and_rows(runs):
    first = runs["first"]
    t = first.timings
    assert set(t) >= {"setup", "compile", "solve", "metrics", "total", "per_scene"}
    assert t["per_scene"] == pytest.approx(t["solve"] / 3)
    # every member closed in the batched call: the driver only took the attempts over
    assert 0.0 <= t["follow_up"] < 0.1 * t["solve"]
    rows = first.rows()
    assert [r["E"] for r in rows] == list(E_FIRST) and all(r["converged"] for r in rows)
    assert set(rows[0]) >= set(METRICS) | {"member", "model", "nu", "steps_he", "residual_he"}


def test_a_batch_whose_lists_overflow_grows_them_and_runs_again(runs, monkeypatch):
    """Pair-list capacities far below what the closed valve needs: the member's lists
    overflow inside the batched program, the batch grows the capacities and runs again,
    and the member closes in the batch, to the state of the batch with room."""
    tiny = pair_lists.Capacities(pt=256, ee=1024, raw_pt=1024, raw_ee=4096, scan_pt=512,
                                 scan_ee=2048, act_pt=128, act_ee=256, table=16384)
    monkeypatch.setattr(pair_lists.Capacities, "for_mesh", classmethod(lambda cls, *a: tiny))
    said = []
    res = simulate_batch(SCENE, stvk(E_FIRST[0]), valve=runs["first"].valve,
                         progress=said.append)
    ref = runs["first"][0]
    assert res.converged
    np.testing.assert_allclose(res[0].x, ref.x, rtol=0, atol=STATE_TOL)
    assert any("1/1 converged in the batch" in m for m in said), said


def test_bad_materials_are_rejected_with_the_member_and_parameter():
    with pytest.raises(ParameterError, match=r"materials\[1\].*differs in model"):
        stack_materials([StVenantKirchhoff(E=1.0), NeoHookean(mu=0.3)])
    with pytest.raises(ParameterError, match=r"materials\[1\].*differs in model or in the "
                                             r"fields set"):
        stack_materials([MassSpring(E1=1.0, E2=1.0, E3=1.0),
                         MassSpring(E1=1.0, E2=1.0, E3=1.0, E1_cf=0.5, E2_cf=0.5, E3_cf=0.5)])
    with pytest.raises(ParameterError, match=r"materials\[2\]: St.Venant-Kirchhoff: E must be "
                                             r"> 0"):
        stack_materials(stvk(1.0, 2.0, -1.0))
    with pytest.raises(ParameterError, match=r"materials\[0\]: Gent: Jm must be finite"):
        stack_materials([Gent(mu=0.3, Jm=float("nan"))])
    with pytest.raises(ParameterError, match="at least one member"):
        stack_materials([])
    with pytest.raises(ParameterError, match=r"materials\[0\] is a float"):
        stack_materials([1.0])
    with pytest.raises(ParameterError, match=r"unknown parameters \['E'\] for the gent model"):
        stack_materials({"E": [1.0]}, template=Gent())
    with pytest.raises(ParameterError, match="same number of values"):
        stack_materials({"mu": [1.0, 2.0], "Jm": [2.3]}, template=Gent())
    with pytest.raises(ParameterError, match="simulate_batch closes valves with the engine"):
        simulate_batch(SCENE.replace(solver="paper"), stvk(1.0))


def test_materials_as_a_dict_over_the_template():
    members, stacked = stack_materials({"E": [0.5, 2.0]},
                                       template=StVenantKirchhoff(E=1.0, nu=0.3))
    assert members == [StVenantKirchhoff(E=0.5, nu=0.3), StVenantKirchhoff(E=2.0, nu=0.3)]
    np.testing.assert_array_equal(stacked.E, [0.5, 2.0])
    np.testing.assert_array_equal(stacked.nu, [0.3, 0.3])
    members, stacked = stack_materials([MassSpring(E1=0.05, E2=0.3, E3=1.2)] * 2)
    assert stacked.E1.shape == (2,) and stacked.E1_cf is None


# ---------------------------------------------------------------------------- the CLI
def _sweep(argv):
    so, se = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(so), contextlib.redirect_stderr(se):
        code = main(["sweep"] + argv)
    return code, so.getvalue(), se.getvalue()


@pytest.mark.parametrize("argv, text", [
    (["--table", "3"], "--table must be 4 (the mass-spring E1 x E2 grid) or 5"),
    (["--table", "4", "--h", "0"], "--h must be a finite mesh size > 0 mm"),
    (["--table", "4", "--h", "nan"], "--h must be a finite mesh size > 0 mm"),
    (["--table", "5", "--metric", "hE"], "--metric must be one of"),
    (["--table", "5", "--models", "stvk", "linear"], "--models: unknown model 'linear'"),
    (["--table", "4", "--E1", "0.1", "-0.2"], "--E1 values must be finite moduli > 0 MPa"),
])
def test_sweep_bad_input_exits_2_naming_the_parameter(argv, text, tmp_path):
    code, out, err = _sweep(argv + ["--out", str(tmp_path / "o")])
    assert code == 2 and text in err and out == ""
    assert not (tmp_path / "o").exists()


def test_sweep_grids_are_the_papers():
    from jaxvalve.cli.sweep import add_parser, table_members
    import argparse
    p = add_parser(argparse.ArgumentParser().add_subparsers())
    (model, members), = table_members(p.parse_args(["--table", "4"]))
    assert model == "mass-spring" and len(members) == 9
    assert {(m.E1, m.E2, m.E3) for _, m in members} == {
        (e1, e2, 1.2) for e1 in (0.05, 0.106, 0.18) for e2 in (0.3, 0.569, 0.7)}
    groups = table_members(p.parse_args(["--table", "5"]))
    assert [g for g, _ in groups] == ["mass-spring", "stvk", "neo-hookean", "gent"]
    mats = {g: [m for _, m in ms] for g, ms in groups}
    assert mats["stvk"] == [StVenantKirchhoff(E=e, nu=0.5) for e in (0.1, 1.0, 10.0)]
    assert mats["gent"] == [Gent(mu=e / 3, Jm=2.3) for e in (0.1, 1.0, 10.0)]
    assert mats["neo-hookean"][1] == NeoHookean(mu=1 / 3)
    assert mats["mass-spring"][2] == MassSpring.linear(10.0)


def test_sweep_writes_csv_and_heat_map(runs, tmp_path):
    """Table 5 restricted to StVK at the second batch's moduli (same compiled solve): the
    CSV holds the batch's numbers, and the heat map is written."""
    out = tmp_path / "sweep"
    before = equilibrium._fire_batch._cache_size()
    code, stdout, stderr = _sweep(
        ["--table", "5", "--models", "stvk", "--E", *map(str, E_SECOND), "--nu", "0.45",
         "--h", "2", "--metric", "h_CC", "--out", str(out)])
    assert code == 0, stderr
    assert equilibrium._fire_batch._cache_size() == before
    assert "[jaxvalve sweep] [########################] 3/3 members" in stderr
    assert "h_C-C" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["table5.csv", "table5.png"]
    assert (out / "table5.png").read_bytes().startswith(PNG)
    rows = list(csv.DictReader(io.StringIO((out / "table5.csv").read_text())))
    assert [r["E"] for r in rows] == ["1.0", "2.0", "0.8"]
    assert [r["converged"] for r in rows] == ["True", "True", "True"]
    assert rows[1]["paper_h"] == "" and rows[0]["paper_h"] == "16.7"   # the paper: E = 1
    for r, m in zip(rows, runs["second"]):
        for k in METRICS:
            assert float(r[k]) == pytest.approx(m.summary()[k], abs=1e-9), k
        assert float(r["residual_closing"]) == m.solves[1].residual
        assert int(r["steps_he"]) == m.solves[0].steps


def test_linear_mass_spring_members_stack_without_the_unused_moduli():
    """The linear law (E2 = E3 = None) stacks like any material; a dict over a linear
    template varies E1, or E2 and E3 together (then the piecewise law), and rejects E2
    alone, naming the member."""
    members, stacked = stack_materials([MassSpring.linear(0.5), MassSpring.linear(2.0)])
    assert stacked.E1.shape == (2,) and stacked.E2 is None and stacked.E3 is None
    assert stacked.is_linear and stacked.stiffest() is stacked
    members, stacked = stack_materials({"E1": [0.5, 2.0]}, template=MassSpring.linear(1.0))
    assert members[1] == MassSpring.linear(2.0) and stacked.is_linear
    members, stacked = stack_materials({"E2": [0.5, 2.0], "E3": [3.0, 3.0]},
                                       template=MassSpring.linear(1.0))
    assert not stacked.is_linear and members[0] == MassSpring(E1=1.0, E2=0.5, E3=3.0)
    with pytest.raises(ParameterError, match=r"materials\[0\]: mass-spring: give E2 and E3 "
                                             r"together"):
        stack_materials({"E2": [0.5]}, template=MassSpring.linear(1.0))
    with pytest.raises(ParameterError, match=r"materials\[1\].*differs in model or in the "
                                             r"fields set"):
        stack_materials([MassSpring.linear(1.0), MassSpring(E1=1.0, E2=1.0, E3=1.0)])
