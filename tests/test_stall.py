"""`jaxvalve.solvers.stall.probe`: a jump of the force is told apart from a slow solve.

The jump is the one that stalls the soft Table 4 valves: under the one-sided contact law
a node behind another sheet's face, further than g0, is penalised while it projects into
the face and not once its projection leaves it."""
import numpy as np
import pytest

from jaxvalve.solvers import stall
from jaxvalve.contact import SmoothContact
from jaxvalve.mechanics.materials import MassSpring
from jaxvalve.mechanics.problem import Params, make_problem


def _two_sheets(one_sided, eps=1e-9):
    """Sheet B: a fixed triangle in z = 0 with normal +z.  Sheet A: a triangle whose one
    free node p lies 0.25 mm behind B (z = -0.25), projecting eps inside B's edge y = 0;
    A's springs are stretched, so its elastic force pulls p across that edge (-y)."""
    x = np.array([[0, 0, 0], [2, 0, 0], [0, 2, 0.0],                    # B
                  [1.0, eps, -0.25], [1.0, -2, -0.25], [2.0, -2, -0.25]])  # A: p, fixed
    ref = np.array([[0, 0], [2, 0], [0, 2.0], [1.0, 0], [1.0, -1], [2.0, -1]])
    prob, ref = make_problem(ref, np.array([[0, 1, 2], [3, 4, 5]]),
                             fixed=np.array([0, 1, 2, 4, 5]), body=np.array([0, 0, 0, 1, 1, 1]))
    law = SmoothContact(stiffness=1.0, gap=0.2, one_sided=one_sided, soft_min=True)
    params = Params(ref=ref, material=MassSpring.linear(1.0), thickness=0.3, pressure=0.0,
                    contact=law)
    return prob, params, x


def test_the_one_sided_contact_jump_at_a_face_edge_is_found_and_named():
    prob, params, x = _two_sheets(one_sided=True)
    rep = stall.probe(prob, params, x, skin=0.5)
    # behind the face at d = 0.25 the energy is (1/2) a (k/2) (g0 + d)^2, a force
    # (1/2) a k (g0 + d) on p (a = 1/6 mm^2, p's lumped reference area), and none once p's
    # projection has left the face (B's nodes are fixed: their reaction is not counted)
    assert rep.jumped and rep.term == "contact" and rep.node == 3
    assert rep.jumps["contact"] == pytest.approx(0.5 * (1 / 6) * 1.0 * (0.2 + 0.25), rel=1e-6)
    assert rep.jumps["elastic"] < 1e-5 and "discontinuous" in rep.cause()
    assert rep.as_dict()["jumped"] is True


def test_a_continuous_force_is_reported_as_a_slow_solve():
    for one_sided, eps in ((False, 1e-9), (True, 0.3)):   # unsigned; or well inside
        prob, params, x = _two_sheets(one_sided, eps)
        rep = stall.probe(prob, params, x, skin=0.5)
        assert not rep.jumped, rep
        assert max(rep.jumps.values()) < stall.STIFFNESS_CAP * rep.step
        assert rep.force > 0.05 and "continuous" in rep.cause()


@pytest.mark.parametrize("E", [0.1, 1.0])
def test_a_residual_below_the_float32_rounding_floor_is_named_as_such(E):
    """An equilibrium solved to 1e-11 in float64: in float32 its residual force lies far
    below the rounding floor, in float64 above its own.  The floor's arithmetic part is
    eps times the cancelling terms; its state part is what the float32 grid of positions
    costs: the float64 residual force at the equilibrium rounded to float32 (the grid's
    nearest point, not the probe's random one) lies within a factor 3 of it."""
    import jax.numpy as jnp
    from jaxvalve.solvers import equilibrium
    from jaxvalve.geometry import meshgen
    from jaxvalve.mechanics.materials import NeoHookean
    from jaxvalve.mechanics.problem import mmhg
    from jaxvalve.solvers import NewtonKrylov
    p, t, b = meshgen.disk(5.0, 2)
    prob, ref = make_problem(p, t, fixed=b)
    params = Params(ref=ref, material=NeoHookean(E), thickness=0.3, pressure=mmhg(80.0))
    sol = equilibrium.solve(prob, params, jnp.asarray(meshgen.lift(p)), NewtonKrylov(rtol=1e-11))
    r32 = stall.probe(prob, params, sol.x, precision="float32")
    r64 = stall.probe(prob, params, sol.x, precision="float64")
    assert r32.force == r64.force and not r32.jumped
    assert r32.floor_arithmetic / r64.floor_arithmetic == pytest.approx(
        np.finfo(np.float32).eps / np.finfo(np.float64).eps)
    # a move within half a float64 spacing rounds back to the same float64 positions
    assert r64.floor_state == 0.0 and r32.floor_state > r32.floor_arithmetic / 10
    rounded = np.asarray(sol.x).astype(np.float32).astype(np.float64)
    at_grid = stall.probe(prob, params, jnp.asarray(rounded)).force
    assert r32.floor_state / 3 < at_grid < 3 * r32.floor_state
    assert r32.at_floor and "rounding floor of float32" in r32.cause()
    assert "spacing of its positions" in r32.cause()
    assert not r64.at_floor and "slow" in r64.cause()


def _hinge(theta_deg):
    """Two triangles sharing the edge 0-1 (the x axis), the second turned by theta_deg
    about it (0: flat): a fold of theta_deg between their normals."""
    t = np.radians(theta_deg)
    ref = np.array([[0.0, 0.0], [1.0, 0.0], [0.4, 0.9], [0.5, -0.8]])
    x = np.array([[0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.4, 0.9, 0.0],
                  [0.5, -0.8 * np.cos(t), -0.8 * np.sin(t)]])
    prob, ref = make_problem(ref, np.array([[0, 1, 2], [1, 0, 3]]), fixed=np.array([0, 1]))
    return prob, ref, x


@pytest.mark.parametrize("theta", [150.0, 150.0 - 0.5 * stall.AT_FOLD_BOUND_DEG, 162.0])
def test_a_barrier_solve_stopped_at_the_fold_bound_names_the_folded_edge(theta):
    """The barrier Newton's line search keeps folds below checks.FOLD_DEG: a solve that
    stopped with an edge at that bound gets a cause naming the edge and its angle; a
    solve stopped with no edge near it (120 degrees), a converged one and one stopped on
    the smooth law's own probe do not."""
    from jaxvalve.contact import BarrierContact
    prob, ref, x = _hinge(theta)
    params = Params(ref=ref, material=MassSpring.linear(1.0), thickness=0.3, pressure=0.0,
                    contact=BarrierContact())
    for result in ("stagnation", "max_steps_reached"):
        cause = stall.stopped_cause(prob, params, result, x, skin=0.5)
        assert cause is not None and "nodes 0 and 1" in cause, cause
        assert f"{theta:.2f} degrees" in cause and "150-degree bound" in cause
        # with self-contact no line search bounds the fold: not the cause
        assert stall.stopped_cause(prob, params, result, x, skin=0.5, fold_bound=False) is None
    assert stall.stopped_cause(prob, params, "successful", x, skin=0.5) is None
    _, _, x120 = _hinge(120.0)
    assert stall.stopped_cause(prob, params, "stagnation", x120, skin=0.5) is None
    assert stall.fold_bound_cause(prob, x120) is None
    assert stall.fold_bound_cause(prob, np.full_like(x, np.nan)) is None
