"""Reference solutions of classical membrane problems, for validation (NumPy/SciPy).

1. Clamped circular membrane under uniform pressure (Foppl-Hencky problem).
   Small-strain, moderate-rotation (Foppl / von Karman) membrane theory, stress-free flat
   disk of radius a, thickness h, Young's modulus E, Poisson ratio nu, edge fixed (u = w = 0
   at r = a), uniform transverse pressure q.  The centre deflection and centre stress are

       w0       = K_w(nu)     * a * (q a / (E h))^(1/3)
       sigma_0  = K_sigma(nu) * (E q^2 a^2 / h^2)^(1/3)

   Hencky (1915) solved the problem by a power series; his numbers contained an arithmetic
   error later corrected by Chien (1948) and Alekseev (1953), see also Fichter (1997, NASA
   TP-3658).  Timoshenko & Woinowsky-Krieger (Theory of Plates and Shells) quote Hencky's original
   K_w = 0.662, K_sigma = 0.423 for nu = 0.3; the corrected values are K_w(0.3) = 0.6534,
   K_sigma(0.3) = 0.4311 (radial stress coefficient b0 = 4 K_sigma = 1.724).  The curve fit
   K_w(nu) ~ 0.7179 - 0.1706 nu - 0.1495 nu^2 of Komaragiri, Begley & Simmonds (2005, J.
   Appl. Mech. 72:203) agrees with `hencky_constants` to 6e-4 over 0.25 <= nu <= 0.5.

   Derivation used here.  With phi = r sigma_r, sigma_theta = d(r sigma_r)/dr (radial
   equilibrium), w' = -q r / (2 h sigma_r) (vertical equilibrium) and compatibility
   eps_r = d(r eps_theta)/dr + w'^2/2, the radial stress obeys, in s = sigma_r / sigma_hat,
   rho = r / a, sigma_hat = (E q^2 a^2 / h^2)^(1/3):

       s'' + 3 s' / rho = -1 / (8 s^2),   s'(0) = 0,   s'(1) + (1 - nu) s(1) = 0

   (the last condition is u(a) = 0, i.e. sigma_theta = nu sigma_r at the edge), and

       w(rho) / (a (q a / (E h))^(1/3)) = 1/2 int_rho^1 t / s(t) dt.

   The ODE does not depend on nu; nu enters only through the edge condition.  It is solved
   with Hencky's power series in rho^2 (default) or by shooting with `solve_ivp`; s(0) is
   found with `brentq`.

2. Inflated spherical membrane (exact finite-strain solution; Green & Adkins 1960,
   Treloar 1975).  A stress-free sphere of radius R, wall thickness H, inflated by internal
   pressure P to radius lambda R (equibiaxial stretch lambda):

       neo-Hookean:  P = 2 mu H / R (1/lambda - 1/lambda^7)
       Gent:         P = 2 mu H Jm / R (1/lambda - 1/lambda^7) / (Jm - 2 lambda^2 - lambda^-4 + 3)

   The neo-Hookean curve has a limit point (maximum pressure) at lambda = 7^(1/6) ~ 1.383;
   `inflated_sphere_stretch` returns the stretch on the stable branch below it.

Units: any consistent set (mm, N, MPa in jaxvalve).
"""
from __future__ import annotations

import functools

import numpy as np
from scipy.integrate import quad, solve_ivp
from scipy.optimize import brentq

__all__ = [
    "hencky_constants", "hencky_center_deflection", "hencky_profile", "hencky_series",
    "sphere_pressure_neo_hookean", "sphere_pressure_gent", "inflated_sphere_stretch",
    "NEO_HOOKEAN_LIMIT_STRETCH",
]

_RHO0 = 1e-6  # start of the shooting integration (regular series below it)


def hencky_series(s0, n_terms: int = 60):
    """Hencky's power series s(rho) = sum_k c_k rho^(2k) of s'' + 3 s'/rho = -1/(8 s^2)
    with s(0) = s0: returns c (n_terms + 1,).  From s^2 L[s] = -1/8, L[s] = s'' + 3 s'/rho
    = sum_j d_j rho^(2j), d_j = 4 (j+1)(j+2) c_(j+1), matched power by power."""
    c = np.zeros(n_terms + 1)
    d = np.zeros(n_terms)
    c[0] = s0
    for j in range(n_terms):
        s2 = np.convolve(c[: j + 1], c[: j + 1])[: j + 1]
        acc = (-0.125 if j == 0 else 0.0) - np.dot(s2[1:], d[:j][::-1])
        d[j] = acc / s2[0]
        c[j + 1] = d[j] / (4.0 * (j + 1) * (j + 2))
    return c


def _series_poly(c):
    """s as a polynomial in rho (even powers only)."""
    coef = np.zeros(2 * len(c) - 1)
    coef[::2] = c
    return np.polynomial.Polynomial(coef)


def _shoot(s0):
    """Integrate s'' + 3 s'/rho = -1/(8 s^2) from rho ~ 0 with s(0) = s0, s'(0) = 0."""
    s2 = -1.0 / (64.0 * s0**2)  # s = s0 + s2 rho^2 + O(rho^4)
    y0 = [s0 + s2 * _RHO0**2, 2.0 * s2 * _RHO0]

    def rhs(r, y):
        return [y[1], -1.0 / (8.0 * y[0] ** 2) - 3.0 * y[1] / r]

    return solve_ivp(rhs, (_RHO0, 1.0), y0, method="DOP853", rtol=1e-13, atol=1e-15,
                     dense_output=True)


@functools.lru_cache(maxsize=64)
def _hencky_solution(nu: float, method: str):
    """(s0, callable s(rho)) solving the edge condition s'(1) + (1 - nu) s(1) = 0."""
    if not -1.0 < nu <= 0.5:
        raise ValueError(f"nu must lie in (-1, 0.5]; got {nu}")
    if method == "series":
        def edge(s0):
            s = _series_poly(hencky_series(s0))
            return s.deriv()(1.0) + (1.0 - nu) * s(1.0)
    elif method == "shooting":
        def edge(s0):
            s, sp = _shoot(s0).y[:, -1]
            return sp + (1.0 - nu) * s
    else:
        raise ValueError(f"method must be 'series' or 'shooting'; got {method!r}")
    s0 = brentq(edge, 0.2, 1.5, xtol=1e-15, rtol=4 * np.finfo(float).eps)
    if method == "series":
        return s0, _series_poly(hencky_series(s0))
    sol = _shoot(s0)
    return s0, lambda r: sol.sol(np.maximum(r, _RHO0))[0]


def hencky_profile(rho, nu: float, method: str = "series"):
    """Dimensionless deflection w(rho) / (a (q a/(E h))^(1/3)) at rho = r/a in [0, 1]."""
    _, s = _hencky_solution(float(nu), method)
    rho = np.atleast_1d(np.asarray(rho, float))
    f = lambda t: t / s(t)
    return np.asarray([0.5 * quad(f, r, 1.0, epsabs=1e-15, epsrel=1e-13, limit=200)[0]
                       for r in rho])


def hencky_constants(nu: float, method: str = "series"):
    """(K_w, K_sigma): w0 = K_w a (q a/(E h))^(1/3), sigma_0 = K_sigma (E q^2 a^2/h^2)^(1/3).

    method: 'series' (Hencky's power series, 60 terms) or 'shooting' (ODE integration);
    they agree to ~1e-14."""
    s0, _ = _hencky_solution(float(nu), method)
    return float(hencky_profile(0.0, nu, method)[0]), float(s0)


def hencky_center_deflection(q, a, E, h, nu):
    """Centre deflection (length) of the clamped Foppl-Hencky membrane."""
    K, _ = hencky_constants(nu)
    return K * a * (q * a / (E * h)) ** (1.0 / 3.0)


# ------------------------------------------------------------------ inflated sphere
NEO_HOOKEAN_LIMIT_STRETCH = 7.0 ** (1.0 / 6.0)


def sphere_pressure_neo_hookean(lam, mu, H, R):
    """Internal pressure that inflates a neo-Hookean sphere (R, H) to stretch lam."""
    lam = np.asarray(lam, float)
    return 2.0 * mu * H / R * (1.0 / lam - lam**-7)


def sphere_pressure_gent(lam, mu, Jm, H, R):
    """Internal pressure that inflates a Gent sphere (R, H, Jm) to stretch lam."""
    lam = np.asarray(lam, float)
    return (2.0 * mu * H * Jm / R * (1.0 / lam - lam**-7)
            / (Jm - 2.0 * lam**2 - lam**-4 + 3.0))


def inflated_sphere_stretch(P, mu, H, R, Jm=None):
    """Stretch lambda of an inflated sphere under pressure P: neo-Hookean (Jm None) or Gent.

    Returns the root on the first (stable) rising branch: for neo-Hookean lambda in
    (1, 7^(1/6)); for Gent lambda in (1, lambda_max) below the first pressure maximum (if
    any) or the stretch limit 2 lam^2 + lam^-4 - 3 = Jm."""
    if Jm is None:
        pressure = lambda l: float(sphere_pressure_neo_hookean(l, mu, H, R))
        hi = NEO_HOOKEAN_LIMIT_STRETCH
    else:
        pressure = lambda l: float(sphere_pressure_gent(l, mu, Jm, H, R))
        # stretch limit: 2 l^2 + l^-4 - 3 = Jm; the first pressure maximum (if any) below it
        lim = brentq(lambda l: 2 * l**2 + l**-4 - 3 - Jm, 1.0 + 1e-12, 1e3)
        ls = np.linspace(1.0 + 1e-9, lim * (1 - 1e-12), 20001)
        drop = np.nonzero(np.diff(sphere_pressure_gent(ls, mu, Jm, H, R)) < 0)[0]
        hi = ls[drop[0]] if drop.size else ls[-1]
    p_max = pressure(hi)
    if not 0 < P < p_max:
        raise ValueError(f"pressure {P} is outside (0, {p_max:.6g}), the stable branch")
    return brentq(lambda l: pressure(l) - P, 1.0 + 1e-14, hi, xtol=1e-15,
                  rtol=4 * np.finfo(float).eps)
