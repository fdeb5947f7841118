"""Validation against classical membrane problems with published answers, with mesh-convergence
rates.  Reference solutions live in `tests/analytic.py`.

1. Clamped circular membrane under uniform pressure (Foppl-Hencky problem; Hencky 1915,
   corrected by Chien 1948).  Stress-free flat disk, radius a, fixed edge, St.Venant-Kirchhoff
   (plane-stress Hooke at small strain).  For small loads the nonlinear model reduces to the
   Foppl / von Karman membrane, whose centre deflection is w0 = K(nu) a (q a/(E h))^(1/3).

   Load: theta = w0/a = 0.02 and 0.04.  Full StVK + follower pressure differs from FvK by
   O(theta^2) relative (u'^2 in the Green strain, sin vs tan of the slope, deformed area and
   direction of the load); measured ~0.16 theta^2, i.e. 6e-5 at theta = 0.02, the same size as
   the finest discretisation error.  The two loads remove it by Richardson extrapolation in
   theta^2: K_h = (4 K_h(theta) - K_h(2 theta)) / 3 is the small-load limit of the discrete
   model, which must converge to K(nu) at the P1 rate O(h^2) (nodal values; the polygonal
   boundary is also an O(h^2) perturbation), h = a / n_rings.

2. Inflated spherical membrane (Green & Adkins 1960; Treloar 1975): a stress-free sphere
   (R, H) of incompressible neo-Hookean or Gent material under internal pressure P inflates
   to lambda R, P = 2 mu H / R (1/lambda - 1/lambda^7) (neo-Hookean).  Meshes: icosphere
   subdivisions 2, 3, 4 (h halves each time), every node free (no boundary conditions: the
   rigid-body modes have zero energy and the net pressure force and torque vanish).

   Expected rate: the reference facets are flat chords of the sphere.  Under a uniform
   dilation lambda of the polyhedron, virtual work gives P = H W'(lambda) / (lambda^2 R_eff)
   with R_eff = 3 V0 / A0 (A0, V0 the polyhedron's area and volume), whereas the smooth
   sphere has R_eff = R.  R_eff = R (1 - c h^2) (facet distance = R cos(circumradius / R)),
   so lambda_h - lambda = -c h^2 f(lambda) / f'(lambda) + ..., f(lambda) = R P(lambda):
   second order, and the discrete sphere inflates less than the continuum.  The test checks
   the rate (2) and also the error itself against this flat-facet prediction.  lambda_h is the
   mean node distance from the centroid divided by R (every reference node lies on the
   sphere of radius R).
"""
import numpy as np
import pytest
import jax.numpy as jnp

import analytic
from jaxvalve.geometry import meshgen
from jaxvalve.solvers.equilibrium import solve
from jaxvalve.mechanics.materials import Gent, NeoHookean, StVenantKirchhoff
from jaxvalve.mechanics.problem import Params, make_problem
from jaxvalve.solvers import FIRE, NewtonKrylov

# one solver object per problem family, so that jit caches are shared between loads.
# Newton cannot start from the flat disk (no out-of-plane stiffness); instead of the default
# FIRE warm start (a second loop to compile) it starts from a paraboloid of the right size.
# rtol 1e-8: the round-off floor of ||F|| / ||F_pressure|| grows as 1/(strain h) (~4e-9 at
# 32 rings, theta = 0.02), and Newton lands well below rtol anyway.
NEWTON = NewtonKrylov(rtol=1e-8, max_steps=100, warm_start=None)
RELAX = FIRE(rtol=1e-10, max_steps=20_000)


def rates(errors):
    """Observed orders log2(e_k / e_{k+1}) for meshes halving h."""
    e = np.abs(np.asarray(errors, float))
    return np.log2(e[:-1] / e[1:])


# ===================================================================== Foppl-Hencky
A_DISK, E, NU, H_DISK = 5.0, 1.0, 0.3, 0.3    # mm, MPa, -, mm
RINGS = (8, 16, 32)
THETAS = (0.02, 0.04)                         # target w0 / a
K_TWK = 0.662                                 # Hencky's 1915 value as quoted by Timoshenko


def hencky_load(theta):
    """Pressure (MPa) whose FvK centre deflection is theta * a, and Q^(1/3) = (qa/Eh)^(1/3)."""
    K, _ = analytic.hencky_constants(NU)
    Q13 = theta / K
    return Q13**3 * E * H_DISK / A_DISK, Q13


@pytest.fixture(scope="module")
def hencky_runs():
    """Per mesh: K_h(theta) (dimensionless centre deflection), the nodal profile
    w_h / (a Q^(1/3)) at each load, and the node radii."""
    out = {}
    for n in RINGS:
        p, t, b = meshgen.disk(A_DISK, n)
        prob, ref = make_problem(p, t, fixed=b)
        rho = np.linalg.norm(p, axis=1) / A_DISK
        prof = []
        for theta in THETAS:
            q, Q13 = hencky_load(theta)
            params = Params(ref=ref, material=StVenantKirchhoff(E, NU), thickness=H_DISK,
                            pressure=q)
            x0 = meshgen.lift(p)
            x0[~b, 2] = theta * A_DISK * (1.0 - rho[~b] ** 2)
            sol = solve(prob, params, jnp.asarray(x0), NEWTON)
            assert float(sol.stats.residual) < 1e-8
            x = np.asarray(sol.x)
            assert np.all(x[b] == meshgen.lift(p)[b])           # clamped edge stays put
            prof.append(x[:, 2] / (A_DISK * Q13))
        prof = np.asarray(prof)                                # (2, N)
        out[n] = dict(K=prof[:, 0], prof=prof, rho=rho)
    return out


def small_load_limit(v):
    """Richardson in theta^2 from (theta, 2 theta): removes the O(theta^2) FvK difference."""
    return (4.0 * v[0] - v[1]) / 3.0


def test_hencky_constant_reference():
    """The reference constant: Hencky's series and ODE shooting agree; the corrected
    literature values are reproduced; Hencky's original 0.662 (Timoshenko) is 1.3% high."""
    K, S = analytic.hencky_constants(0.3)
    K2, S2 = analytic.hencky_constants(0.3, method="shooting")
    assert abs(K - K2) < 1e-10 and abs(S - S2) < 1e-10
    assert round(K, 4) == 0.6534                       # corrected Hencky (Chien 1948)
    assert round(4 * S, 3) == 1.724                    # radial stress series b0 = 1.724
    assert 0.012 < K_TWK / K - 1 < 0.014               # the 1915 arithmetic error
    # Komaragiri, Begley & Simmonds (2005) fit K(nu) = 0.7179 - 0.1706 nu - 0.1495 nu^2
    for nu in (0.25, 0.3, 0.4, 0.45, 0.5):
        fit = 0.7179 - 0.1706 * nu - 0.1495 * nu**2
        assert abs(analytic.hencky_constants(nu)[0] - fit) < 1e-3
    # the profile: w(1) = 0 and decreasing in rho
    w = analytic.hencky_profile(np.linspace(0, 1, 6), 0.3)
    assert w[-1] == 0 and np.all(np.diff(w) < 0) and abs(w[0] - K) < 1e-13


def test_hencky_centre_deflection_converges_at_second_order(hencky_runs):
    K, _ = analytic.hencky_constants(NU)
    Kh = np.array([small_load_limit(hencky_runs[n]["K"]) for n in RINGS])
    err = (Kh - K) / K
    r = rates(err)
    print("\nHencky centre deflection: rings", RINGS, "rel. error", err, "rates", r)
    assert np.all(err > 0)                    # the P1 membrane is too soft here, monotonically
    assert np.all(np.diff(np.abs(err)) < 0)
    assert np.all(r > 1.7) and np.all(r < 2.3), r
    assert abs(err[-1]) < 3e-4
    # Richardson in h (order 2) from the two finest meshes lands on K(nu) to 2e-5
    K_rich = Kh[-1] + (Kh[-1] - Kh[-2]) / 3.0
    assert abs(K_rich / K - 1) < 5e-5
    # ... and rules out Hencky's uncorrected 1915 constant
    assert abs(K_rich / K_TWK - 1) > 0.01
    # without the small-load extrapolation (theta = 0.02 itself) the error is still < 0.05%
    assert abs(hencky_runs[RINGS[-1]]["K"][0] / K - 1) < 5e-4


def test_hencky_load_scaling(hencky_runs):
    """w0 ~ q^(1/3): doubling theta changes w0/(a Q^(1/3)) only at O(theta^2), by a
    mesh-independent amount (a property of the nonlinear model, not of the mesh)."""
    d = np.array([hencky_runs[n]["K"][1] / hencky_runs[n]["K"][0] - 1 for n in RINGS])
    assert np.all(d > 0) and np.all(d < 1e-3)
    assert np.ptp(d) < 0.05 * d.mean()


def test_hencky_profile_converges(hencky_runs):
    """Max nodal deflection error over the whole membrane, small-load limit, decays as h^2."""
    K, _ = analytic.hencky_constants(NU)
    err = []
    for n in RINGS:
        run = hencky_runs[n]
        rho_u, inv = np.unique(np.round(run["rho"], 12), return_inverse=True)
        w_ref = analytic.hencky_profile(rho_u, NU)[inv]
        err.append(np.max(np.abs(small_load_limit(run["prof"]) - w_ref)) / K)
    r = rates(err)
    print("\nHencky profile: max nodal error / w0", err, "rates", r)
    assert np.all(r > 1.7), r
    assert err[-1] < 5e-4


# ===================================================================== inflated sphere
R_S, H_S, MU = 5.0, 0.3, 0.1     # mm, mm, MPa
SUBDIV = (2, 3, 4)


def sphere_runs(material, P):
    """Per subdivision: (lambda_h, flat-facet prediction, radius spread, centroid drift)."""
    out = []
    for s in SUBDIV:
        p, t = meshgen.icosphere(R_S, s)
        prob, ref = make_problem(p, t)                      # every node free
        params = Params(ref=ref, material=material, thickness=H_S, pressure=P)
        sol = solve(prob, params, jnp.asarray(p), RELAX)
        assert float(sol.stats.residual) < 1e-10
        x = np.asarray(sol.x)
        c = x.mean(axis=0)
        r = np.linalg.norm(x - c, axis=1)
        V0 = np.sum(np.einsum("ij,ij->i", p[t[:, 0]], np.cross(p[t[:, 1]], p[t[:, 2]]))) / 6
        A0 = 0.5 * np.sum(np.linalg.norm(np.cross(p[t[:, 1]] - p[t[:, 0]],
                                                   p[t[:, 2]] - p[t[:, 0]]), axis=1))
        Jm = getattr(material, "Jm", None)
        pred = analytic.inflated_sphere_stretch(P, material.mu, H_S, 3 * V0 / A0, Jm=Jm)
        out.append((r.mean() / R_S, pred, r.std() / r.mean(), np.linalg.norm(c)))
    return np.array(out)


def check_sphere(runs, lam, label):
    lam_h, pred, spread, drift = runs.T
    err = lam_h - lam
    r = rates(err)
    print(f"\n{label}: subdivisions {SUBDIV} lambda error {err} rates {r}, "
          f"flat-facet prediction error {pred - lam}")
    assert np.all(err < 0)                              # flat facets: R_eff < R, stiffer
    assert np.all(r > 1.8) and np.all(r < 2.2), r
    assert abs(err[-1]) < 2e-3 * lam
    # the discretisation error is the flat-facet effective-radius effect, to 2%
    assert np.all(np.abs(lam_h - pred) < 0.02 * np.abs(err))
    # the inflated shape is a sphere to O(h^2), and rigid modes did not drift
    assert np.all(rates(spread) > 1.7) and spread[-1] < 2e-4
    assert np.all(drift < 1e-10 * R_S)


def test_inflated_sphere_neo_hookean():
    lam = 1.25                                          # below the limit point 7^(1/6) = 1.383
    P = float(analytic.sphere_pressure_neo_hookean(lam, MU, H_S, R_S))
    assert abs(analytic.inflated_sphere_stretch(P, MU, H_S, R_S) - lam) < 1e-12
    check_sphere(sphere_runs(NeoHookean(MU), P), lam, "neo-Hookean sphere")


def test_inflated_sphere_gent():
    lam, Jm = 1.3, 2.3
    P = float(analytic.sphere_pressure_gent(lam, MU, Jm, H_S, R_S))
    assert abs(analytic.inflated_sphere_stretch(P, MU, H_S, R_S, Jm=Jm) - lam) < 1e-12
    # Gent stiffening removes the limit point: this pressure exceeds the largest one a
    # neo-Hookean sphere can hold (at lambda = 7^(1/6)), yet the Gent sphere is stable
    lim = analytic.NEO_HOOKEAN_LIMIT_STRETCH
    assert P > analytic.sphere_pressure_neo_hookean(lim, MU, H_S, R_S)
    check_sphere(sphere_runs(Gent(MU, Jm), P), lam, "Gent sphere")
