"""The template optimisation (optimize/): targets, objective, adjoint gradients through the
closure, the optax loop, its files, resume and errors."""
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from jaxvalve import Scene
from jaxvalve.cli import main
from jaxvalve.errors import ParameterError
from jaxvalve.mechanics.materials import NeoHookean
from jaxvalve.geometry.template import Template, template_area
from optimize import (Evaluator, Objective, Target, optimize_template, parse_target,
                      targets_from_dict)
from optimize.objective import chord

BASE = (12.0, 7.1, 15.0)


def test_targets_parse_and_penalise():
    t = parse_target("h_c >= 4")
    assert (t.metric, t.lower, t.upper, t.value) == ("h_c", 4.0, None, None)
    assert parse_target("h=8").value == 8.0
    t2 = parse_target("3.5<=h_CC<=6")
    assert (t2.lower, t2.upper) == (3.5, 6.0)
    assert parse_target("ncca<=50").metric == "NCCA_pct"
    # penalty: zero inside, quadratic outside, in units of scale
    assert float(t.penalty(5.0)) == 0.0
    assert float(t.penalty(3.0)) == pytest.approx(1.0)
    assert float(t2.penalty(7.0)) == pytest.approx(1.0)
    assert float(Target("h", value=8.0, weight=2.0, scale=0.5).penalty(9.0)) == pytest.approx(8.0)
    assert targets_from_dict({"h_c": {"lower": 4}, "h": "h=8"})[1].value == 8.0


@pytest.mark.parametrize("bad, match", [
    ("h_q>=4", "unknown metric 'h_q'"),
    ("5<=h<=4", "contradictory: lower bound 5.0 > upper bound 4.0"),
    ("h>>4", "cannot read target"),
])
def test_bad_targets_raise_clear_errors(bad, match):
    with pytest.raises(ParameterError, match=match):
        parse_target(bad)
    assert main(["optimize", "--target", bad, "--out", "unused"]) == 2


def test_bad_objective_and_start_inputs(capsys):
    with pytest.raises(ParameterError, match="both"):
        Target("h", lower=1.0, value=2.0)
    with pytest.raises(ParameterError, match=r"bounds\['b'\] must satisfy 0 < lower < upper"):
        Objective(bounds={"b": (20.0, 10.0)})
    with pytest.raises(ParameterError, match="unknown parameter 'alpha'"):
        Objective(bounds={"alpha": (100.0, 170.0)})
    with pytest.raises(ParameterError, match="size_weight must be a finite number >= 0"):
        Objective(size_weight=-1.0)
    with pytest.raises(ParameterError, match="unknown keys"):
        targets_from_dict({"h": {"lowr": 3}})
    assert main(["optimize", "--bounds", "b=3", "--out", "unused"]) == 2
    assert main(["optimize", "--b", "5", "--out", "unused"]) == 2       # 2b < |AD|
    assert "template b must exceed" in capsys.readouterr().err


def test_objective_terms_are_the_formulas_and_differentiable():
    obj = Objective(targets=(Target("h", value=8.0),), size_weight=0.1, margin=0.5,
                    constraint_weight=100.0)
    rab = jnp.asarray(BASE)
    A = Template(*BASE, 160.0).area
    terms = obj.terms(rab, 160.0, {"h": 9.0}, 20.0, A)
    assert float(terms["target:h"]) == pytest.approx(1.0)
    assert float(terms["size"]) == pytest.approx(0.1)
    assert float(terms["constraint:validity"]) == 0.0          # 2b - |AD| = 4.5 mm
    # inside the margin the constraint grows quadratically: slack 0.25 mm -> (0.5)^2 * 100
    assert float(terms["constraint:free_edge"]) == 0.0
    t2 = obj.terms(rab, 160.0, {"h": 9.0}, 30.0 - 0.25, A)
    assert float(t2["constraint:free_edge"]) == pytest.approx(25.0)
    assert float(chord(12.0, 7.1, 160.0)) == pytest.approx(Template(*BASE, 160.0).chord)
    # the template part of the objective: autodiff == central differences
    f = lambda x: obj.value(x, 160.0, {"h": 9.0}, 29.8, A)   # noqa: E731
    g = jax.grad(f)(rab)
    for k in range(3):
        e = np.zeros(3)
        e[k] = 1e-6
        fd = (float(f(rab + e)) - float(f(rab - e))) / 2e-6
        assert float(g[k]) == pytest.approx(fd, rel=1e-6)
    assert float(jax.grad(lambda b: template_area(12.0, 7.1, b, 160.0, jnp))(15.0)) > 0


@pytest.fixture(scope="module")
def evaluator():
    """Benchmark root at h = 2.5 mm, both loads at 3 mmHg (coarse meshes do not close at
    80 mmHg; docs/known-limits.md), targets around the start so every term is active."""
    sc = Scene(h=2.5, pressure=3.0, rtol=1e-9, max_steps=100_000)
    obj = Objective(targets=(Target("h_c", lower=30.0), Target("h", value=8.0),
                             Target("h_E", lower=22.0)), size_weight=0.1,
                    area_ref=Template(*BASE, 160.0).area)
    return Evaluator(sc, obj)


def test_objective_gradient_through_the_closures_matches_central_differences(evaluator):
    """The adjoint gradient against central differences of re-closed valves, to 3e-3: each
    closure's smooth-metric plan (its annulus level and candidate sets) is rebuilt at its
    state, and the gradient holds it fixed."""
    ev = evaluator
    e0 = ev.forward(BASE)
    assert e0.converged and set(ev.loads) == {"he", "closed"}
    v, g, info = ev.gradient(e0)
    assert v == pytest.approx(e0.value, rel=1e-12)
    assert all(a.residual < 1e-9 for a in info["adjoint"])
    for k in range(3):
        d = np.zeros(3)
        d[k] = 1e-3
        fp, fm = ev.forward(np.add(BASE, d), e0), ev.forward(np.subtract(BASE, d), e0)
        fd = (fp.value - fm.value) / 2e-3
        assert abs(g[k] - fd) < 3e-3 * abs(fd), (k, g[k], fd)


def test_metric_sensitivities_to_template_and_modulus_match_central_differences(evaluator):
    """d(each smooth metric)/d(r, a, b, E) by the LU adjoint vs central differences of
    warm-started closures, to 5e-3 (each closure's metric plan is rebuilt at its state
    and held fixed by the adjoint); E enters only through the traced material (no
    recompile)."""
    import dataclasses

    ev = evaluator
    e0 = ev.forward(BASE)
    sens = ev.sensitivities(e0)
    assert set(sens) == {"h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c"}
    assert set(sens["h"]) >= {"r", "a", "b", "E", "nu"}
    checks = []
    for k, name in enumerate(("r", "b")):
        d = np.zeros(3)
        d[[0, 2][k]] = 1e-3
        fp, fm = ev.forward(np.add(BASE, d), e0), ev.forward(np.subtract(BASE, d), e0)
        checks += [(m, name, (fp.metrics[m] - fm.metrics[m]) / 2e-3) for m in sens]

    def at_E(E):
        return ev.forward(BASE, e0, material=dataclasses.replace(ev.material, E=E)).metrics
    E0 = float(ev.material.E)
    mp, mm = at_E(E0 * (1 + 1e-4)), at_E(E0 * (1 - 1e-4))
    checks += [(m, "E", (mp[m] - mm[m]) / (2e-4 * E0)) for m in sens]
    n = 0
    for m, name, fd in checks:
        if abs(fd) > 1e-2:                  # a derivative that is there (else only small)
            assert abs(sens[m][name] - fd) < 5e-3 * abs(fd), (m, name, sens[m][name], fd)
            n += 1
        else:
            assert abs(sens[m][name] - fd) < 1e-4, (m, name, sens[m][name], fd)
    assert n >= 10
    with pytest.raises(ParameterError, match="must be a StVenantKirchhoff"):
        ev.forward(BASE, e0, material=NeoHookean(0.3))
    with pytest.raises(ParameterError, match="E must be"):
        ev.forward(BASE, e0, material=dataclasses.replace(ev.material, E=-1.0))


def test_loop_descends_writes_its_files_and_resumes_exactly(evaluator, tmp_path):
    sc, obj = evaluator.scene, evaluator.objective
    kw = dict(evaluator=evaluator, max_step=0.5, figures=False, verify=False)
    full = optimize_template(sc, obj, max_iter=2, out=tmp_path / "full", **kw)
    f = [r["objective"] for r in full.records]
    assert len(f) == 3 and f[2] < f[1] < f[0]                  # Armijo: strict decrease
    assert full.counts["gradient"] == 3 and full.counts["forward"] >= 3
    doc = json.loads((tmp_path / "full" / "trajectory.json").read_text())
    assert [r["objective"] for r in doc["records"]] == f
    assert doc["status"]["check"] is None                      # verify=False
    header = (tmp_path / "full" / "trajectory.csv").read_text().splitlines()[0].split(",")
    for col in ("iteration", "r", "a", "b", "objective", "grad_norm", "m:h", "m:h_E",
                "f:size", "seconds", "forward", "gradient"):
        assert col in header
    part = optimize_template(sc, obj, max_iter=1, out=tmp_path / "part", **kw)
    assert part.records[-1]["iteration"] == 1
    resumed = optimize_template(sc, obj, max_iter=2, out=tmp_path / "part", resume=True, **kw)
    np.testing.assert_allclose(resumed.rab, full.rab, rtol=0, atol=1e-7)
    assert resumed.value == pytest.approx(full.value, rel=1e-7)
    with pytest.raises(ParameterError, match="differ"):
        optimize_template(sc.replace(E=2.0), obj, max_iter=2, out=tmp_path / "part",
                          resume=True)
    with pytest.raises(ParameterError, match="another scene, eps or objective"):
        optimize_template(sc, Objective(obj.targets, size_weight=0.2,
                                        area_ref=obj.area_ref), evaluator=evaluator)


def test_bad_start_and_non_finite_objective_stop_with_a_reason(evaluator, monkeypatch,
                                                               tmp_path):
    sc, obj = evaluator.scene, evaluator.objective
    with pytest.raises(ParameterError, match="outside the bounds"):
        optimize_template(sc, Objective(obj.targets, area_ref=obj.area_ref,
                                        bounds={"r": (13.0, 16.0)}), evaluator=evaluator)
    monkeypatch.setattr(evaluator, "gradient",
                        lambda ev, adjoint="lu": (float("nan"), np.zeros(3), {"adjoint": []}))
    with pytest.raises(Exception, match="not finite"):
        optimize_template(sc, obj, evaluator=evaluator, max_iter=1, out=tmp_path)
    status = json.loads((tmp_path / "trajectory.json").read_text())["status"]
    assert status["failed"] and "not finite" in status["reason"]


def test_warm_starts_and_the_final_check_from_the_placement(evaluator):
    """warm_start=False closes from the placement whatever the warm start.  Path
    dependence is reported, never passed off as the design's objective: a closure from
    the placement that disagrees with the run's, or does not converge, makes the result
    inconsistent with a message that says so."""
    import dataclasses

    from optimize import run as run_mod

    sc, obj = evaluator.scene, evaluator.objective
    # warm_start=False: a closure ignores the warm start and repeats the placement's
    e0 = evaluator.forward(BASE)
    steps = lambda e: [x["steps"] for x in e.solves]  # noqa: E731
    warm = steps(evaluator.forward(BASE, e0))                      # warm: from converged
    assert all(w <= c for w, c in zip(warm, steps(e0))) and sum(warm) < sum(steps(e0))
    evaluator.warm_start = False
    try:
        e1 = evaluator.forward(BASE, e0)
    finally:
        evaluator.warm_start = True
    assert steps(e1) == steps(e0) and e1.value == e0.value
    # a warm-started step, then the check's closure from the placement: the same state
    ok = optimize_template(sc, obj, evaluator=evaluator, max_iter=1, max_step=0.2,
                           figures=False)
    assert ok.records[-1]["iteration"] == 1 and ok.check["converged"]
    gap = abs(ok.check["value"] - ok.value) / ok.value
    assert ok.consistent == (gap <= 1e-3) and ("path-dependent" in ok.check["message"]) \
        == (not ok.consistent)

    class OtherBranch:       # its closure from the placement lands on another state
        def __init__(self, **change):
            self.change = change

        def forward(self, rab, warm=None):
            assert warm is None
            return dataclasses.replace(ok.evaluation, **self.change)

    state = dataclasses.make_dataclass("S", ["rab", "value", "evaluation"])(
        ok.rab, ok.value, ok.evaluation)
    check = run_mod._verify(OtherBranch(value=1.5 * ok.value), state, 1e-3)
    assert not check["consistent"] and check["converged"]
    assert "path-dependent" in check["message"]
    assert check["value"] == pytest.approx(1.5 * ok.value, rel=1e-12)
    check = run_mod._verify(OtherBranch(converged=False, reason="stalled (test)"), state,
                            1e-3)
    assert not check["consistent"] and not check["converged"]
    assert "does not close from the placement" in check["message"]


def test_cli_exits_3_when_the_final_check_disagrees(monkeypatch, tmp_path, capsys):
    """`jaxvalve optimize` passes --cold-closures / --no-check through, prints the run,
    and exits with 3 when the final design closes differently from the placement."""
    import optimize
    from optimize.run import OptimizationResult

    seen = {}

    def fake(scene, objective, **kw):
        seen.update(kw, scene=scene)
        rec = dict(iteration=0, objective=1.0, **{"m:h": 8.0})
        check = None if not kw["verify"] else dict(converged=True, value=2.0, metrics={},
                                                   consistent=False, message="WARNING")
        return OptimizationResult(np.array(BASE), 1.0, [rec], "test", False,
                                  dict(forward=1, gradient=1), 0.1, 0.0, None, (), check)

    monkeypatch.setattr(optimize, "optimize_template", fake)
    assert main(["optimize", "--out", str(tmp_path)]) == 3
    assert seen["warm_start"] is True and seen["verify"] is True
    # without flags the CLI closes as the Python function does without a scene
    assert seen["scene"] == optimize.run.default_scene()
    assert seen["scene"].rtol == optimize.run.OPTIMIZE_RTOL < Scene().rtol
    assert main(["optimize", "--rtol", "1e-5", "--max-steps", "700", "--out",
                 str(tmp_path)]) == 3
    assert (seen["scene"].rtol, seen["scene"].max_steps) == (1e-5, 700)
    assert main(["optimize", "--cold-closures", "--no-check", "--out", str(tmp_path)]) == 0
    assert seen["warm_start"] is False and seen["verify"] is False
    with pytest.raises(ParameterError, match="verify_rtol must be a finite number > 0"):
        optimize.run.optimize_template(Scene(), Objective(), verify_rtol=float("nan"))
    with pytest.raises(ParameterError, match="warm_start must be True or False"):
        optimize.run.optimize_template(Scene(), Objective(), warm_start="no")


def test_a_closure_stopped_at_its_step_cap_is_reported_with_its_residual(evaluator,
                                                                         monkeypatch):
    """The evaluator reports a closure stopped at its cap as `simulate` does: not
    converged, the result and the residual in its reason, an infinite objective."""
    monkeypatch.setattr(evaluator, "scene", evaluator.scene.replace(max_steps=20))
    ev = evaluator.forward(BASE)
    assert not ev.converged and "max_steps_reached" in ev.reason and "residual" in ev.reason
    assert ev.value == float("inf") and not ev.solves[-1]["converged"]


