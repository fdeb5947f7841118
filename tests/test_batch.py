"""`simulate_batch`: one valve closed under a batch of materials (vmap under one jit).

One coarse valve (h = 2 mm, StVK; it converges there for E >= 1 MPa in 1226-1432 FIRE steps
at 3 mmHg and 341-520 at 80 mmHg) is closed once as a batch of three members, once more as
another batch of three, and once per member by `simulate`, for the whole module (the
compiles dominate the time).  The `jaxvalve sweep` test reuses the batch's compiled solve.
"""
import contextlib
import csv
import io

import numpy as np
import pytest

from jaxvalve import Scene, simulate
from jaxvalve import batch as B
from jaxvalve.batch import METRICS, BatchResult, simulate_batch, stack_materials
from jaxvalve.cli import main
from jaxvalve.errors import ConvergenceError, ParameterError
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.solvers import RESULTS

#: the batched FIRE program's own mechanics (frozen members, step caps, recompiles): no
#: barrier fallback for the members that stop at the cap (`jaxvalve.valve.closure`; a batch
#: member closed by the fallback: tests/test_closure_driver.py)
SCENE = Scene(h=2.0, model="stvk", max_steps=2000, fallback=False)
E_FIRST = (1.0, 2.0, 3.0)   # E = 1.1-1.5 MPa end with leaflets crossing on this mesh
# E = 0.8 MPa does not converge at 80 mmHg on this mesh (its residual stalls near 1e-2), so
# it runs to max_steps while its companions have finished: their results must stay frozen
E_SECOND = (1.0, 2.0, 0.8)

PNG = b"\x89PNG\r\n\x1a\n"


def stvk(*es):
    return [StVenantKirchhoff(E=e, nu=0.45) for e in es]


@pytest.fixture(scope="module")
def runs():
    first = simulate_batch(SCENE, stvk(*E_FIRST), throw=False)
    cache = B._close_batch._cache_size()
    with pytest.raises(ConvergenceError) as err:
        simulate_batch(SCENE, stvk(*E_SECOND), valve=first.valve)
    second = err.value.solution
    seq = [simulate(SCENE.replace(E=e), valve=first.valve) for e in E_FIRST]
    return dict(first=first, second=second, error=str(err.value), seq=seq,
                cache=(cache, B._close_batch._cache_size()))


def test_batch_equals_sequential_simulate_for_every_member(runs):
    first, seq = runs["first"], runs["seq"]
    assert isinstance(first, BatchResult) and first.converged and len(first) == 3
    for m, s in zip(first, seq):
        assert m.parameters == {"E": s.scene.E, "nu": 0.45}
        np.testing.assert_allclose(m.x_he, s.x_he, rtol=0, atol=1e-9)
        np.testing.assert_allclose(m.x, s.x, rtol=0, atol=1e-9)
        for a, b in zip(m.solves, s.solves):
            assert (a.result, a.converged, a.steps) == (b.result, b.converged, b.steps)
            assert a.residual == pytest.approx(b.residual, rel=1e-9)
        for k in METRICS:
            assert m.summary()[k] == pytest.approx(s.summary()[k], abs=1e-9), k
    # the members took different paths (so a frozen member was carried along)
    assert len({m.solves[0].steps for m in first}) == 3


def test_member_result_does_not_depend_on_its_batch(runs):
    """E = 1 MPa with companions that finish earlier (E = 2) and much later (E = 0.8, to
    max_steps): bit for bit the same as in the first batch."""
    a, b = runs["first"][0], runs["second"][0]
    assert b.parameters["E"] == 1.0 and b.converged
    np.testing.assert_array_equal(a.x, b.x)
    np.testing.assert_array_equal(a.x_he, b.x_he)
    assert [s.steps for s in a.solves] == [s.steps for s in b.solves]
    assert runs["second"][1].solves[1].steps < runs["second"][2].solves[1].steps == 2000


def test_new_material_values_do_not_recompile(runs):
    before, after = runs["cache"]
    assert before == after
    assert runs["second"].timings["compile"] < 0.5
    assert runs["first"].timings["compile"] > 1.0


def test_unconverged_member_is_reported_with_its_residual(runs):
    second, msg = runs["second"], runs["error"]
    assert not second.converged and second.failed == [2]
    bad = second[2]
    he, closing = bad.solves
    assert he.converged and not closing.converged and not bad.converged
    assert closing.result == "max_steps_reached" and closing.steps == SCENE.max_steps
    assert np.isfinite(closing.residual) and closing.residual > SCENE.rtol
    # the ConvergenceError names the member, its parameters, load, result and residual
    assert "1 of 3 members did not converge" in msg
    assert "member 2 (stvk: E=0.8, nu=0.45)" in msg
    assert f"80 mmHg: max_steps_reached, residual {closing.residual:.3e}" in msg
    row = second.rows()[2]
    assert row["converged"] is False and row["residual_closing"] == closing.residual
    assert row["result_closing"] == "max_steps_reached" and row["steps_closing"] == 2000
    assert row["limit_pressure_closing"] is None        # a limit pressure only at a limit
    # and why it stopped (`jaxvalve.solvers.stall`): in the member's report, the error and the row
    assert closing.cause and closing.cause in msg and row["cause_closing"] == closing.cause
    assert he.cause is None and row["cause_he"] == ""
    # its (finite, unconverged) state is still measured, as simulate(throw=False) does
    assert bad.measured and all(np.isfinite(v) for v in bad.summary().values())


def test_timings_and_rows(runs):
    first = runs["first"]
    t = first.timings
    assert set(t) >= {"setup", "compile", "solve", "metrics", "total", "per_scene", "retries"}
    assert t["per_scene"] == pytest.approx(t["solve"] / 3) and t["retries"] == 0
    # every member closed in the batched call: the closure driver only took the attempts
    # over (no solve of its own), a small part of the solve time
    assert 0.0 <= t["follow_up"] < 0.1 * t["solve"]
    rows = first.rows()
    assert [r["E"] for r in rows] == list(E_FIRST) and all(r["converged"] for r in rows)
    assert set(rows[0]) >= set(METRICS) | {"member", "model", "nu", "steps_he", "residual_he"}


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
    for bad in (-1, 1.5, True, "2"):
        with pytest.raises(ParameterError, match=r"handoff must be an integer >= 0"):
            simulate_batch(SCENE, stvk(1.0), handoff=bad)


def test_materials_as_a_dict_over_the_template():
    members, stacked = stack_materials({"E": [0.5, 2.0]},
                                       template=StVenantKirchhoff(E=1.0, nu=0.3))
    assert members == [StVenantKirchhoff(E=0.5, nu=0.3), StVenantKirchhoff(E=2.0, nu=0.3)]
    np.testing.assert_array_equal(stacked.E, [0.5, 2.0])
    np.testing.assert_array_equal(stacked.nu, [0.3, 0.3])
    members, stacked = stack_materials([MassSpring(E1=0.05, E2=0.3, E3=1.2)] * 2)
    assert stacked.E1.shape == (2,) and stacked.E1_cf is None


def _fake_batch(calls, overflow):
    """A stand-in for the compiled batch: member results tagged by call, and the pair
    list overflow that ``overflow(call, E) -> (overflowed, max_group)`` says."""
    def fake(sub, problem, base, x0, nbrs, pressures, settings, **kw):
        E = np.asarray(sub.E)
        calls.append((E.tolist(), nbrs.capacity, nbrs.soft_capacity))
        over, group = np.array([overflow(len(calls), e) for e in E]).T
        over = over.astype(bool)
        shape = (len(E), 2)
        col = lambda v: np.broadcast_to(np.asarray(v)[:, None], shape).copy()
        return dict(x=np.zeros(shape + x0.shape) + len(calls),
                    result=col(np.where(over, int(RESULTS.neighbour_overflow), 0)),
                    steps=np.full(shape, 10 * len(calls)), residual=np.full(shape, 1e-5),
                    base_overflow=col(over), count=np.full(shape, 3 * nbrs.capacity),
                    n_scan=np.zeros(shape, int), max_group=col(group.astype(int)),
                    soft_overflow=np.zeros(shape, bool), soft_count=np.zeros(shape, int))
    return fake


def _retry(runs, monkeypatch, overflow):
    valve = runs["first"].valve
    members, stacked = stack_materials(stvk(1.0, 1.1, 1.2))
    base = valve.params(members[0], 3.0, SCENE.contact_law(), bending=SCENE.bending_law())
    calls, said = [], []
    monkeypatch.setattr(B, "_close_batch", _fake_batch(calls, overflow))
    stages, _, _, retries = B._run_batch(members, stacked, valve, base, np.zeros(2),
                                         SCENE.make_solver(), 1.0, True, said.append)
    return stages, retries, calls, said


def test_overflowing_members_are_solved_again_at_a_larger_capacity(runs, monkeypatch):
    """The host-side retry: members whose pair list overflowed (and only they) are solved
    again with a grown capacity, and their results replace the first ones."""
    stages, retries, calls, said = _retry(
        runs, monkeypatch, lambda call, e: (call == 1 and e == 1.1, 10))
    assert retries == 1 and len(calls) == 2
    assert calls[0][0] == [1.0, 1.1, 1.2] and calls[1][0] == [1.1]
    assert calls[1][1] == 2 * 3 * calls[0][1] and calls[1][2] == calls[0][2]
    for st in stages:
        assert st["steps"].tolist() == [10, 20, 10] and (st["result"] == 0).all()
        assert (st["x"][1] == 2).all() and (st["x"][0] == 1).all()
    assert "overflowed for members [1]" in said[0]


def test_members_that_keep_overflowing_are_reported_not_raised(runs, monkeypatch):
    """A member whose overflow no capacity cures (a node with more than MAX_GROUP
    candidates) is not retried; one that overflows at every capacity is given up after
    _MAX_RETRIES; both keep the result neighbour_overflow, the others are unaffected."""
    from jaxvalve.contact.neighbours import MAX_GROUP
    stages, retries, calls, said = _retry(
        runs, monkeypatch,
        lambda call, e: (e != 1.0, MAX_GROUP + 1 if e == 1.2 else 10))
    assert retries == B._MAX_RETRIES and len(calls) == B._MAX_RETRIES + 1
    assert [c[0] for c in calls[1:]] == [[1.1]] * B._MAX_RETRIES
    overflow = int(RESULTS.neighbour_overflow)
    for st in stages:
        assert st["result"].tolist() == [0, overflow, overflow]
    assert any("more than" in m and "[2]" in m for m in said)
    assert "still overflowed after 6 retries" in said[-1]


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


def test_sweep_writes_csv_and_heat_map_and_exits_3_when_a_member_fails(runs, tmp_path):
    """Table 5 restricted to StVK at the second batch's moduli (same compiled solve): the
    CSV holds the batch's numbers, the E = 0.8 MPa member is flagged, the exit code is 3."""
    out = tmp_path / "sweep"
    code, stdout, stderr = _sweep(
        ["--table", "5", "--models", "stvk", "--E", *map(str, E_SECOND), "--nu", "0.45",
         "--h", "2", "--max-steps", "2000", "--metric", "h_CC", "--no-fallback",
         "--out", str(out)])
    assert code == 3
    assert B._close_batch._cache_size() == runs["cache"][1]     # the batch's compiled solve
    assert "did NOT converge" in stderr and "E=0.8" in stderr and "max_steps_reached" in stderr
    assert "[jaxvalve sweep] [########################] 3/3 members" in stderr
    assert "h_C-C" in stdout and "NO" in stdout
    assert sorted(p.name for p in out.iterdir()) == ["table5.csv", "table5.png"]
    assert (out / "table5.png").read_bytes().startswith(PNG)
    rows = list(csv.DictReader(io.StringIO((out / "table5.csv").read_text())))
    assert [r["E"] for r in rows] == ["1.0", "2.0", "0.8"]
    assert [r["converged"] for r in rows] == ["True", "True", "False"]
    assert rows[1]["paper_h"] == "" and rows[0]["paper_h"] == "16.7"   # the paper: E = 1
    for r, m in zip(rows, runs["second"]):
        for k in METRICS:
            assert float(r[k]) == pytest.approx(m.summary()[k], abs=1e-9), k
        assert float(r["residual_closing"]) == m.solves[1].residual
        assert int(r["steps_he"]) == m.solves[0].steps


def test_vectorised_batch_agrees_with_sequential_and_one_member_is_a_single_solve(runs):
    """The GPU default path on this CPU.  vectorize=True runs the members' steps, and their
    pair-list rebuilds (`vmap_control.branches("select")`), as one array program: members then
    differ from sequential runs by rounding, amplified along FIRE's path, but each is an
    equilibrium to rtol (the member that finishes last takes its last steps alone, by the
    default hand-off).  A batch of one runs the unbatched single-solve program."""
    first, seq = runs["first"], runs["seq"]
    vec = simulate_batch(SCENE, stvk(E_FIRST[0], E_FIRST[2]), valve=first.valve,
                         vectorize=True)
    assert vec.vectorized and vec.converged
    for m, s in zip(vec, (seq[0], seq[2])):
        assert all(ms.residual <= SCENE.rtol for ms in m.solves)
        assert abs(m.solves[1].steps - s.solves[1].steps) <= 0.2 * s.solves[1].steps
        for k in METRICS:
            assert m.summary()[k] == pytest.approx(s.summary()[k], abs=0.02), k
    one = simulate_batch(SCENE, stvk(E_FIRST[1]), valve=first.valve, vectorize=True)
    m, s = one[0], seq[1]
    assert [x.steps for x in m.solves] == [x.steps for x in s.solves]
    np.testing.assert_allclose(m.x, s.x, rtol=0, atol=1e-9)
    np.testing.assert_allclose(m.x_he, s.x_he, rtol=0, atol=1e-9)


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
