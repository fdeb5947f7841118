"""`jaxvalve.stall.probe`: a jump of the force is told apart from a slow solve.

The jump is the one that stalls the soft Table 4 valves: under the one-sided contact law
a node behind another sheet's face, further than g0, is penalised while it projects into
the face and not once its projection leaves it."""
import numpy as np
import pytest

from jaxvalve import stall
from jaxvalve.contact import SmoothContact
from jaxvalve.materials import MassSpring
from jaxvalve.problem import Params, make_problem


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


def test_a_residual_below_the_float32_rounding_floor_is_named_as_such():
    """An equilibrium solved to 1e-11 in float64: in float32 its residual force lies far
    below the rounding floor (eps32 times the cancelling terms), in float64 above its own."""
    import jax.numpy as jnp
    from jaxvalve import equilibrium, meshgen
    from jaxvalve.materials import NeoHookean
    from jaxvalve.problem import mmhg
    from jaxvalve.solvers import NewtonKrylov
    p, t, b = meshgen.disk(5.0, 2)
    prob, ref = make_problem(p, t, fixed=b)
    params = Params(ref=ref, material=NeoHookean(0.1), thickness=0.3, pressure=mmhg(80.0))
    sol = equilibrium.solve(prob, params, jnp.asarray(meshgen.lift(p)), NewtonKrylov(rtol=1e-11))
    r32 = stall.probe(prob, params, sol.x, precision="float32")
    r64 = stall.probe(prob, params, sol.x, precision="float64")
    assert r32.force == r64.force and not r32.jumped
    assert r32.floor / r64.floor == pytest.approx(np.finfo(np.float32).eps
                                                  / np.finfo(np.float64).eps)
    assert r32.at_floor and "rounding floor of float32" in r32.cause()
    assert not r64.at_floor and "slow" in r64.cause()
