"""A start past the material's stretch limit (`jaxvalve.valve.closure.admissible_start`).

The placement is a harmonic surface, not an equilibrium: on the h = 3 mm benchmark valve
its most stretched triangle has I1 + 1/I2 - 3 = 0.23, and settled at 0 mmHg it has
0.016.  A Gent valve whose Jm lies between the two has equilibria that no solve from the
placement reaches (its energy is infinite there); the driver starts it from the settled
placement, and refuses a Jm below the settled stretch before any load is solved.
"""
import numpy as np
import pytest

from jaxvalve import Scene
from jaxvalve.errors import ParameterError
from jaxvalve.mechanics import materials as M
from jaxvalve.simulation import build_scene_valve
from jaxvalve.solvers import RESULTS
from jaxvalve.valve import closure
from jaxvalve.valve import model as V
from jaxvalve.valve.checks import gent_invariant

SCENE = Scene(h=3.0, model="gent", max_steps=4000)


@pytest.fixture(scope="module")
def valve():
    return build_scene_valve(SCENE)


@pytest.fixture(scope="module")
def stretch(valve):
    """max I1 + 1/I2 - 3 of the placement and of the placement settled at 0 mmHg."""
    settled, _ = V.settle(valve, M.NeoHookean(mu=1.0 / 3.0))
    placed = float(gent_invariant(valve.ref, valve.triangles, valve.x_start).max())
    rest = float(gent_invariant(valve.ref, valve.triangles, settled.x_start).max())
    assert rest < 0.25 * placed       # the placement is far from rest
    return placed, rest


def test_the_limit_free_relative_of_gent_is_neo_hookean_and_others_are_their_own():
    g = M.Gent(mu=0.2, Jm=0.5)
    assert isinstance(g.limit_free(), M.NeoHookean) and g.limit_free().mu == 0.2
    for m in (M.NeoHookean(mu=0.2), M.StVenantKirchhoff(), M.MassSpring()):
        assert m.limit_free() is m


@pytest.mark.parametrize("model", ["stvk", "neo-hookean", "mass-spring"])
def test_a_law_without_a_limit_starts_where_it_is_given(valve, model):
    scene = SCENE.replace(model=model)
    x = np.asarray(valve.x_start)
    assert closure.admissible_start(valve, scene, x) is x


def test_gent_inside_its_limit_at_the_placement_starts_there(valve, stretch):
    scene = SCENE.replace(Jm=2.0 * stretch[0])
    x = np.asarray(valve.x_start)
    assert closure.admissible_start(valve, scene, x) is x


def test_gent_past_its_limit_at_the_placement_closes_from_the_settled_placement(
        valve, stretch, monkeypatch):
    placed, rest = stretch
    jm = 0.1
    assert rest < jm < placed
    scene = SCENE.replace(Jm=jm)
    x = closure.admissible_start(valve, scene, np.asarray(valve.x_start))
    g = gent_invariant(valve.ref, valve.triangles, x)
    assert g.max() == pytest.approx(rest, rel=1e-6)
    (ls,) = closure.close_valve(valve, scene, pressures=(3.0,))
    assert ls.converged, ls.report.describe()
    assert gent_invariant(valve.ref, valve.triangles, ls.x).max() < jm
    assert V.state_failure(valve, ls.x) is None
    # the same closure from the placement: no solve gets past the first step
    monkeypatch.setattr(closure, "admissible_start", lambda v, s, x, **kw: x)
    (bad,) = closure.close_valve(valve, scene, pressures=(3.0,))
    assert not bad.converged and bad.report.result == RESULTS.stretch_limit.name


def test_gent_past_its_limit_even_at_rest_is_refused_before_any_load(valve, stretch,
                                                                      monkeypatch):
    rest = stretch[1]
    calls = []
    monkeypatch.setattr(closure.V, "close", lambda *a, **kw: calls.append(a))
    scene = SCENE.replace(Jm=0.5 * rest)
    with pytest.raises(ParameterError, match=r"Jm = .* must exceed (\d|\.)+") as e:
        closure.close_valve(valve, scene)
    assert f"{rest:.3g}" in str(e.value)
    assert calls == []


def test_a_batch_member_past_its_limit_at_rest_is_refused_before_the_batched_program(
        valve, stretch, monkeypatch):
    from jaxvalve import batch, simulate_batch
    ran = []
    monkeypatch.setattr(batch, "_batched_load", lambda *a, **kw: ran.append(a))
    members = [M.Gent(mu=1.0 / 3.0, Jm=2.3), M.Gent(mu=1.0 / 3.0, Jm=0.5 * stretch[1])]
    with pytest.raises(ParameterError, match="Jm"):
        simulate_batch(SCENE, members, valve=valve)
    assert ran == []


def test_a_batch_settles_a_member_past_its_limit_once_and_closes_it(valve, stretch,
                                                                   monkeypatch):
    from jaxvalve import simulate_batch
    settles = []
    real = V.settle
    monkeypatch.setattr(closure.V, "settle",
                        lambda *a, **kw: settles.append(1) or real(*a, **kw))
    members = [M.Gent(mu=1.0 / 3.0, Jm=2.3), M.Gent(mu=1.0 / 3.0, Jm=0.1)]
    res = simulate_batch(SCENE, members, valve=valve)
    assert len(settles) == 1                  # the second member, once
    for m in res.members:
        assert m.converged, m.describe() if hasattr(m, "describe") else m
        assert gent_invariant(valve.ref, valve.triangles, m.x).max() < m.material.Jm


def test_the_optimiser_settles_a_design_past_its_limit_and_closes_it(stretch, monkeypatch):
    """The optimiser's evaluator starts each design where the driver starts `simulate`:
    a Gent design whose placement passes Jm is settled at 0 mmHg on its own (mapped)
    reference first; from the placement its closure fails at the stretch limit.  On the
    barrier path (the smooth law lets these h = 3 mm leaflets cross; `simulate` falls
    back to the barrier there, the evaluator does not)."""
    import optimize.evaluate as E
    from optimize import Evaluator, Objective, Target
    scene = SCENE.replace(Jm=0.1)
    ev = Evaluator(scene, Objective(targets=(Target("h_E", value=15.0),)))
    rab = (scene.r, scene.a, scene.b)
    good = ev.forward(rab)
    assert good.converged, good.reason
    x = np.asarray(good.states["he"][1].x)
    assert gent_invariant(ev.design_valve(rab).ref, ev.valve.triangles, x).max() < 0.1
    monkeypatch.setattr(E, "admissible_start", lambda v, s, x, **kw: x)
    bad = ev.forward(rab)
    assert not bad.converged
    assert bad.solves[-1]["result"] == RESULTS.stretch_limit.name
