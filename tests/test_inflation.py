"""The inflation analysis of a material (`jaxvalve.mechanics.inflation`): the peak of a
spherical balloon's pressure-stretch curve, found from the material's own energy, against
closed forms and against a finite-element balloon of the same material."""
import numpy as np
import pytest
import jax.numpy as jnp

import analytic
from jaxvalve.errors import ParameterError
from jaxvalve.geometry import meshgen
from jaxvalve.mechanics.inflation import balloon_pressure, inflation_limit
from jaxvalve.mechanics.materials import Gent, MassSpring, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import MMHG, Params, make_problem
from jaxvalve.solvers import FIRE, RESULTS
from jaxvalve.solvers.equilibrium import solve

H = 0.3


def test_neo_hookean_peaks_at_the_closed_form():
    mu = 0.05 / 3
    lim = inflation_limit(NeoHookean(mu), H)
    assert lim.stretch == pytest.approx(analytic.NEO_HOOKEAN_LIMIT_STRETCH, rel=1e-7)
    R = 7.0
    assert lim.pressure(R) * MMHG == pytest.approx(float(analytic.sphere_pressure_neo_hookean(
        analytic.NEO_HOOKEAN_LIMIT_STRETCH, mu, H, R)), rel=1e-9)
    lam = np.linspace(1.01, 3.0, 7)
    np.testing.assert_allclose(balloon_pressure(NeoHookean(mu), H, lam),
                               R * analytic.sphere_pressure_neo_hookean(lam, mu, H, R),
                               rtol=1e-12)
    # the radius that explains a limit pressure inverts the pressure of a radius
    assert lim.radius(lim.pressure(R)) == pytest.approx(R, rel=1e-12)


def test_springs_peak_at_a_stretch_of_two():
    """Three linear springs to a triangle: w = 3/2 E (lambda - 1)^2, so P R0 = 3 E H
    (lambda - 1) / lambda^2, which peaks at lambda = 2 with 3 E H / 4."""
    E = 0.1
    lim = inflation_limit(MassSpring.linear(E), H)
    assert lim.stretch == pytest.approx(2.0, rel=1e-7)
    assert lim.pr == pytest.approx(0.75 * E * H, rel=1e-9)


def test_piecewise_springs_peak_on_their_stiffest_segment():
    """Eq. 3.3's springs: past break2 the stress is sig2 + E3 (eps - break2), so
    P R0 = 3 H (E3 lambda - c) / lambda^2 with c = E3 (1 + break2) - sig2, which peaks at
    lambda = 2 c / E3."""
    E1, E2, E3, b1, b2 = 0.05, 0.3, 1.2, 0.175, 0.3
    sig2 = E1 * b1 + E2 * (b2 - b1)
    c = E3 * (1 + b2) - sig2
    lam = 2 * c / E3
    lim = inflation_limit(MassSpring(E1=E1, E2=E2, E3=E3), H)
    assert lim.stretch == pytest.approx(lam, rel=1e-7)
    assert lim.pr == pytest.approx(3 * H * (E3 * lam - c) / lam**2, rel=1e-9)


def test_gent_peaks_only_where_jm_is_large():
    """A Gent balloon has a pressure maximum only for a large Jm (it tends to the
    neo-Hookean one as Jm grows); the project's default Jm = 2.3 stiffens first."""
    mu = 0.1 / 3
    assert not inflation_limit(Gent(mu=mu, Jm=2.3), H).exists
    for jm in (50.0, 1e4):
        lim = inflation_limit(Gent(mu=mu, Jm=jm), H)
        lam = np.linspace(1.0001, analytic.NEO_HOOKEAN_LIMIT_STRETCH * 1.2, 200_001)
        p = analytic.sphere_pressure_gent(lam, mu, jm, H, 1.0)
        i = int(np.argmax(p))
        assert lim.stretch == pytest.approx(lam[i], abs=2e-5)
        assert lim.pr == pytest.approx(p[i], rel=1e-8)
    assert lim.stretch == pytest.approx(analytic.NEO_HOOKEAN_LIMIT_STRETCH, rel=1e-4)


def test_stvk_has_no_inflation_limit():
    lim = inflation_limit(StVenantKirchhoff(E=0.05), H)
    assert not lim.exists and lim.pressure(5.0) == np.inf and np.isnan(lim.radius(60.0))
    assert "stiffens" in lim.describe(60.0) and "no inflation limit" in lim.describe()
    g = balloon_pressure(StVenantKirchhoff(E=0.05), H, np.linspace(1.01, 8.0, 50))
    assert np.all(np.diff(g) > 0)


def test_a_finite_element_balloon_of_springs_bursts_at_the_predicted_pressure():
    """An icosphere of linear springs (the valve's mass-spring model) holds 0.99 of the
    analysed limit at its effective radius 3 V0 / A0 (`tests/test_limit_point.py`) and
    runs away at 1.01 of it."""
    R, E = 5.0, 0.1
    p, t = meshgen.icosphere(R, 2)
    prob, ref = make_problem(p, t)
    v0 = np.sum(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]]))) / 6
    a0 = 0.5 * np.sum(np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]],
                                              p[t[:, 2]] - p[t[:, 0]]), axis=1))
    lim = inflation_limit(MassSpring.linear(E), H)
    p_max = lim.pressure(3 * v0 / a0) * MMHG          # MPa
    out = {}
    for f in (0.99, 1.01):
        params = Params(ref=ref, material=MassSpring.linear(E), thickness=H,
                        pressure=f * p_max)
        s = solve(prob, params, jnp.asarray(p), FIRE(rtol=1e-8, max_steps=20_000),
                  throw=False)
        x = np.asarray(s.x)
        out[f] = (int(s.result), np.linalg.norm(x - x.mean(0), axis=1).mean() / R)
    assert out[0.99][0] == RESULTS.successful and 1.5 < out[0.99][1] < lim.stretch
    assert out[1.01][0] == RESULTS.escaped and out[1.01][1] > 2.5


def test_bad_input_is_refused():
    with pytest.raises(ParameterError, match="thickness"):
        inflation_limit(NeoHookean(0.1), 0.0)
    with pytest.raises(ParameterError, match="stretch_max"):
        inflation_limit(NeoHookean(0.1), H, stretch_max=1.0)
    with pytest.raises(ParameterError, match="mu"):
        inflation_limit(NeoHookean(-0.1), H)
    with pytest.raises(ParameterError, match="thickness"):
        balloon_pressure(NeoHookean(0.1), float("nan"), [1.2])
    from jaxvalve.mechanics.inflation import compression_limit, uniaxial_stress
    with pytest.raises(ParameterError, match="stretch_min"):
        compression_limit(StVenantKirchhoff(0.05), stretch_min=1.5)
    with pytest.raises(ParameterError, match="every stretch"):
        uniaxial_stress(StVenantKirchhoff(0.05), [0.5, float("nan")])
    with pytest.raises(ParameterError, match="E"):
        compression_limit(StVenantKirchhoff(-0.05))
    lim = inflation_limit(NeoHookean(0.1), H)
    with pytest.raises(ParameterError, match="radius must be finite and > 0 mm"):
        lim.pressure(0.0)
    with pytest.raises(ParameterError, match="pressure must be finite and > 0 mmHg"):
        lim.radius(float("nan"))


@pytest.mark.parametrize("nu", [0.45, 0.3])
def test_stvk_loses_its_compressive_stiffness_at_one_over_root_three(nu):
    """In uniaxial stress (lateral stress free) StVK's Green strain law S = E_Y E11 gives
    the nominal stress E_Y lam (lam^2 - 1) / 2, for any nu: its compressive extreme, where
    the material's own stiffness turns negative, is at lam = 1/sqrt(3)."""
    from jaxvalve.mechanics.inflation import compression_limit, uniaxial_stress
    m = StVenantKirchhoff(0.05, nu)
    lam = np.array([0.3, 0.5, 0.8, 1.0, 1.3])
    np.testing.assert_allclose(uniaxial_stress(m, lam), 0.05 * lam * (lam**2 - 1) / 2,
                               rtol=1e-9, atol=1e-14)
    assert compression_limit(m) == pytest.approx(1 / np.sqrt(3), rel=1e-8)


def test_neo_hookean_gent_and_springs_keep_their_compressive_stiffness():
    """Incompressible neo-Hookean in uniaxial stress: mu (lam - 1/lam^2), stiffening as it
    is compressed; so do Gent and the springs: no compression limit."""
    from jaxvalve.mechanics.inflation import compression_limit, uniaxial_stress
    mu = 0.05 / 3
    lam = np.array([0.2, 0.5, 0.9, 1.0, 1.5])
    np.testing.assert_allclose(uniaxial_stress(NeoHookean(mu), lam), mu * (lam - lam**-2),
                               rtol=1e-9, atol=1e-14)
    for m in (NeoHookean(mu), Gent(mu, 2.3), MassSpring.linear(0.05)):
        assert compression_limit(m) is None, m
