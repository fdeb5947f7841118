"""FIRE (Bitzek et al. 2006, Guenole et al. 2020): damped inertial relaxation."""
from __future__ import annotations

import dataclasses

import jax.numpy as jnp

from ..vmap_control import cond_each
from ..errors import ParameterError
from .base import RESULTS, check_settings, check_state, force_and_scale


@dataclasses.dataclass(frozen=True)
class FIRE:
    """FIRE with per-node masses equal to the stiffness bound (N/mm), so that every mode has
    angular frequency <= 1 and ``dt_max`` is dimensionless.  Masses are refreshed every
    ``refresh`` steps (stiffening materials).  Stops at relative residual < rtol.

    A step that would leave the admissible set (a triangle past the Gent stretch limit, or
    collapsed) is not taken: the state stays, the velocity is zeroed and dt halved, as on
    uphill motion.  Inertia near the Gent limit, where the stiffness rises without bound,
    otherwise carries the state past the limit (a failure) although an equilibrium lies
    inside it.  Only once dt falls below ``dt_min`` (no admissible step) does the solve
    stop, as `RESULTS.stretch_limit`.

    patience: the solve stops as `RESULTS.stagnation` once its best relative residual has
    not halved for this many steps (0: never).  On the benchmark valve (four models at
    h = 1.5 mm, three at 0.88 mm, 3 and 80 mmHg) the longest stretch without a halving
    was 459 steps, on the soft leaflets of the paper's Table 4 at 3 mmHg 690; at 80 mmHg
    those soft valves last halve their best residual by step 242-3056 and then wander for
    the rest of the step cap, which cost 50 000 steps before the fallback could start
    (docs/mechanics.md, "FIRE's patience")."""

    rtol: float = 1e-6
    max_steps: int = 50_000
    dt_start: float = 0.1
    dt_max: float = 1.0
    n_min: int = 5
    f_inc: float = 1.1
    f_dec: float = 0.5
    alpha_start: float = 0.1
    f_alpha: float = 0.99
    refresh: int = 100
    dt_min: float = 1e-6
    patience: int = 5000
    #: a stagnated FIRE solve is not given a shorter load step by continuation in
    #: pressure (`jaxvalve.solvers.continuation.cut_on`): its stall is the contact law's roughness
    #: or a nearly free mode, not the length of the load step
    cut_on = ()

    def __post_init__(self):
        check_settings(self, dict(rtol="positive", max_steps="count", dt_start="positive",
                                  dt_max="positive", n_min="count", f_inc="above_one",
                                  f_dec="unit", alpha_start="unit", f_alpha="unit_closed",
                                  refresh="positive_count", dt_min="positive",
                                  patience="count"))
        if not self.dt_min < self.dt_start <= self.dt_max:
            raise ParameterError(f"FIRE needs dt_min < dt_start <= dt_max; got dt_min="
                                 f"{self.dt_min}, dt_start={self.dt_start}, "
                                 f"dt_max={self.dt_max}")

    def _mass(self, system, y, args):
        b = system.bound(y, args)
        return jnp.where(system.free, b, 1.0)[:, None]

    #: The force at y0 is computed by the first step, not by `init` (see `init`).
    lazy_force = True

    def init(self, system, y, args):
        # Step 0 is a null step: with F = 0 and v = 0 it does not move y, and its force
        # evaluation gives F(y0).  So the force (and the masses, set at step 0) are traced
        # once, inside the loop: a second traced copy in `init` cost ~3 s of compile on
        # the benchmark valve.  `terminate` does not stop before step 0 has run.
        return dict(F=jnp.zeros_like(y), v=jnp.zeros_like(y),
                    m=jnp.ones((y.shape[0], 1), y.dtype),
                    dt=jnp.asarray(self.dt_start, y.dtype),
                    alpha=jnp.asarray(self.alpha_start, y.dtype),
                    npos=jnp.asarray(0), n=jnp.asarray(0), evals=jnp.asarray(0),
                    refused=jnp.asarray(False), admissible=jnp.asarray(True),
                    r=jnp.asarray(jnp.inf, y.dtype), scale=jnp.asarray(1.0, y.dtype),
                    best=jnp.asarray(jnp.inf, y.dtype), mark=jnp.asarray(0))

    def step(self, system, y, args, s):
        F, v = s["F"], s["v"]
        # masses: set at the first step, raised every `refresh` steps (stiffening).  Under
        # vmap only the members due compute them (`vmap_control.cond_each`); a member that has
        # finished (``args["active"]`` False, `iterate`) is never due
        floor = jnp.where(s["n"] == 0, 0.0, s["m"])
        due = (s["n"] % self.refresh == 0) & args.get("active", True)
        m = cond_each(due, lambda m, f, y, a: jnp.maximum(f, self._mass(system, y, a)),
                      lambda m, f, y, a: m, s["m"], floor, y, args)
        sq = jnp.sqrt(m)
        f = F / sq  # force in mass-scaled coordinates; v is the scaled velocity
        power = jnp.sum(f * v)
        first = s["n"] == 0            # the null step: F = v = 0, so dy = 0 below
        up = power > 0
        npos = jnp.where(up, s["npos"] + 1, 0)
        grow = up & (npos > self.n_min)
        dt = jnp.where(grow, jnp.minimum(s["dt"] * self.f_inc, self.dt_max),
                       jnp.where(up | first, s["dt"], s["dt"] * self.f_dec))
        alpha = jnp.where(grow, s["alpha"] * self.f_alpha,
                          jnp.where(up | first, s["alpha"], self.alpha_start))
        # on uphill motion: step back half a step and stop (FIRE 2.0)
        y0 = y
        y = jnp.where(up, y, y - 0.5 * s["dt"] * v / sq)
        v = jnp.where(up, v, 0.0)
        v = v + dt * f
        vn = jnp.linalg.norm(v)
        fn = jnp.linalg.norm(f)
        v = (1.0 - alpha) * v + alpha * vn * f / jnp.where(fn > 0, fn, 1.0)
        dy = dt * v / sq
        big = jnp.max(jnp.linalg.norm(dy, axis=-1))
        dy = dy * jnp.minimum(1.0, args["max_move"] / jnp.where(big > 0, big, 1.0))
        y = y + dy
        F, scale = force_and_scale(system, y, args)
        # a step out of the admissible set is refused: back to y0 (whose force is s["F"]),
        # at rest, with half the time step (the null step 0 is never refused: F(y0) is new)
        admissible = system.admissible(y, args)
        refuse = ~first & ~admissible
        y = jnp.where(refuse, y0, y)
        F = jnp.where(refuse, s["F"], F)
        scale = jnp.where(refuse, s["scale"], scale)
        v = jnp.where(refuse, 0.0, v)
        dt = jnp.where(refuse, dt * self.f_dec, dt)
        alpha = jnp.where(refuse, self.alpha_start, alpha)
        npos = jnp.where(refuse, 0, npos)
        n = s["n"] + 1
        # the relative residual at y, measured once a step, here, for the patience and for
        # `terminate`, with the scale (||F_pressure||) from the force's own pressure load;
        # at rest (P = 0) the scale is F(y0), which the loop sets after the null step 0
        # (`iterate`) and `force_and_scale` gives the same here
        r = jnp.linalg.norm(F) / jnp.where(scale > 0, scale, 1.0)
        # patience: the step at which the best residual last halved (from step 1)
        best, mark = s["best"], s["mark"]
        if self.patience > 0:
            halved = ~first & (r < 0.5 * best)
            best, mark = jnp.where(halved, r, best), jnp.where(halved, n, mark)
        return y, dict(F=F, v=v, m=m, dt=dt, alpha=alpha, npos=npos, n=n, evals=s["evals"] + 1,
                       refused=refuse, admissible=admissible | refuse, r=r, scale=scale,
                       best=best, mark=mark)

    def terminate(self, system, y, args, s):
        started = s["n"] > 0                      # F is the force at y after step 0
        ok = started & (s["r"] < self.rtol)     # the step measured it at y
        # the step checked y's stretch (a refused step keeps y0, admissible since step 0)
        bad = jnp.where(started, check_state(system, y, args, s["F"], s["admissible"]), -1)
        # refused steps shrank dt to nothing: every step from y leaves the admissible set
        # (dt also shrinks on uphill motion: that alone is no reason to stop)
        stuck = s["refused"] & (s["dt"] < self.dt_min)
        bad = jnp.where((bad < 0) & stuck, RESULTS.stretch_limit, bad)
        stalled = (self.patience > 0) & (s["n"] - s["mark"] > self.patience)
        bad = jnp.where((bad < 0) & ~ok & stalled, RESULTS.stagnation, bad)
        return ok | (bad >= 0), jnp.where(bad >= 0, bad, RESULTS.successful)

    def stats(self, s):
        return dict(force_evals=s["evals"], hvps=jnp.asarray(0))
