"""One scene's closures and smooth coaptation metrics as functions of theta = (r, a, b).

`Evaluator(scene, objective)` owns the mesh, the valve, the differentiable design map
(`jaxvalve.valve.design`) and two compiled functions:

* ``forward(rab, warm)``: the closures the objective needs (3 mmHg for h_E, 80 mmHg for the
  other metrics; a closure no target needs is skipped), each warm-started from the
  previous evaluation's state with the sutured nodes moved to the new template, then the
  smooth metrics on a `SmoothPlan` built at the new state, and the objective, together
  with its partial derivatives at fixed states (one compiled program, `_terms`).
* ``gradient(ev)``: the objective's value and its gradient with respect to (r, a, b).
  The equilibria enter through the implicit adjoint: one solve K^T mu = df/dx per
  closure (`jaxvalve.solvers.adjoint.solve_lu`), pulled back to (r, a, b) by `pullback`
  (`jaxvalve.solvers.adjoint.residual_vjp`).  It never re-runs or unrolls the solver.

Changing theta changes only traced values: nothing recompiles, unless the mapped mesh
degrades (an angle below ``min_angle``), when the new template is meshed afresh (a new
``generation``, with new shapes, so the functions compile again).
"""
from __future__ import annotations

import dataclasses
import time

import jax
import jax.numpy as jnp
import numpy as np

from jaxvalve.contact.pairs import min_distance
from jaxvalve.solvers.adjoint import fixed_pairs, residual_vjp, solve_lu
from jaxvalve.valve.closure import admissible_start, close_load
from jaxvalve import valve as V
from jaxvalve.coaptation import annulus_level
from jaxvalve.coaptation.smooth import smooth_metrics, smooth_plan
from jaxvalve.valve.design import ValveDesign
from jaxvalve.errors import ConvergenceError, ParameterError
from jaxvalve.geometry.leaflet_mesh import mesh_leaflet
from jaxvalve.geometry.template import Template
from jaxvalve.geometry.template_map import template_map

from .objective import Objective
from .targets import METRICS

__all__ = ["Evaluator", "Evaluation"]

LOAD_ORDER = ("he", "closed")


@dataclasses.dataclass(frozen=True)
class Evaluation:
    """The objective at one template.

    rab (3,) mm; generation: the mesh it was computed on; states {load: (x0 (N, 3),
    `Solution`)}; plans {load: SmoothPlan}; metrics {name: float} (smooth, METRICS
    units); terms {name: float}; value: f; d_cc: commissure distance (mm); solves: one
    dict per closure (load, pressure, converged, result, steps, residual, seconds);
    converged: every closure converged (else value is inf and ``reason`` says why);
    partials: (df/d(r, a, b) (3,) at fixed states, {load: df/dx (N, 3)}), computed with
    the metrics by one program, for `Evaluator.gradient` (None when not converged)."""

    rab: np.ndarray
    generation: int
    states: dict
    plans: dict
    metrics: dict
    terms: dict
    value: float
    d_cc: float
    solves: tuple
    converged: bool
    reason: str = ""
    partials: tuple | None = None


class Evaluator:
    """scene: the `jaxvalve.Scene` (root, mesh size h, material, loads, solver tolerance);
    its r, a, b are the start and its alpha stays fixed.  objective: `Objective`.
    eps (mm): smoothing width of the metrics; min_angle (degrees): remesh threshold;
    mesh_at: (r, a, b) to mesh at (default the start; a resumed run meshes where the
    interrupted one last meshed).  warm_start: start each closure from the given earlier
    evaluation's closed state (default; about 3x cheaper) or, when False, always from
    the placement, so that the objective is a function of (r, a, b) alone (contact can
    make the closed state depend on where the closure starts; README Known limits)."""

    def __init__(self, scene, objective: Objective, *, eps: float = 0.1,
                 min_angle: float = 15.0, progress=None, mesh_at=None,
                 warm_start: bool = True):
        if scene.solver != "engine":
            raise ParameterError(f"optimisation needs solver='engine' (the barrier contact; "
                                 f"the paper's contact law has no adjoint); got "
                                 f"{scene.solver!r}")
        if not (0 < eps <= 0.5):
            raise ParameterError(f"eps must be in (0, 0.5] mm; got {eps}")
        self.scene, self.objective, self.eps, self.min_angle = scene, objective, eps, min_angle
        self.loads = tuple(l for l in LOAD_ORDER if l in objective.loads)
        self.pressure = {"he": scene.he_pressure, "closed": scene.pressure}
        self.material, self.contact = scene.material(), scene.contact_law()
        self.bending = scene.bending_law()
        self.say = progress or (lambda s: None)
        if not isinstance(warm_start, bool):
            raise ParameterError(f"warm_start must be True or False; got {warm_start!r}")
        self.warm_start = warm_start
        self.generation = 0
        self.compiles = 0
        self._build(np.array([scene.r, scene.a, scene.b] if mesh_at is None else mesh_at,
                             float))

    # ------------------------------------------------------------------ setup
    def theta(self, rab):
        """(r, a, b, alpha) (4,) as a host array."""
        return np.concatenate([np.asarray(rab, np.float64), [float(self.scene.alpha)]])

    def _theta_traced(self, rab):
        """(r, a, b, alpha) (4,) inside a traced function of rab (3,)."""
        return jnp.concatenate([rab, jnp.asarray([self.scene.alpha], rab.dtype)])

    def _build(self, rab):
        sc = self.scene.replace(r=float(rab[0]), a=float(rab[1]), b=float(rab[2]))
        lm = mesh_leaflet(sc.template(), sc.h)
        self.valve = V.build_valve(sc.load_root(), lm)
        self.design = ValveDesign.build(self.valve, template_map(lm))
        self.base = {l: self.valve.params(self.material, self.pressure[l], self.contact,
                                          sc.thickness, np.deg2rad(sc.fibre_angle),
                                          self.bending) for l in self.loads}
        self.generation += 1
        self.mesh_at = np.asarray(rab, float)
        self.capacity = self.w_band = None
        self._direct_jit = jax.jit(jax.value_and_grad(
            lambda rab, xs, st, pl, ar: self._terms(rab, xs, st, pl, ar),
            argnums=(0, 1), has_aux=True))
        self._design_pull_jit = jax.jit(self._design_pullback)
        self._metric_jac_jit = jax.jit(jax.jacrev(self._load_metrics, argnums=(0, 2)),
                                       static_argnums=(1,))
        self._dcc_jit = jax.jit(self.d_cc)
        # host-side maps, compiled once per mesh (eager jax.numpy would compile each op)
        self._x_fixed_jit = jax.jit(self.design.x_fixed)
        self._ref_jit = jax.jit(self.design.ref)
        self.say(f"mesh generation {self.generation}: {len(lm.triangles)} triangles a "
                 f"leaflet at (r, a, b) = {tuple(np.round(rab, 4))}")

    def d_cc(self, theta):
        """Distance (mm) between a leaflet's two commissures (ends of its path)."""
        L = 2 * theta[1] + jnp.pi * theta[0] * theta[3] / 180.0
        p = self.design.paths(L)[0]
        return jnp.linalg.norm(jnp.asarray(p)[-1] - jnp.asarray(p)[0])

    def _plan(self, x):
        v = self.valve
        s0 = annulus_level(x, np.asarray(v.problem.fixed), v.body, v.root.axis, v.root.origin)
        kw = dict(axis=v.root.axis, origin=v.root.origin, annulus_level=s0,
                  g_c=self.scene.g_c, eps_max=self.eps)
        if self.capacity is not None:
            try:
                return smooth_plan(x, v.triangles, v.body, v.free_edge,
                                   capacity=self.capacity, w_band=self.w_band, **kw)
            except ParameterError:       # more candidates or a wider band: grow them
                pass
        plan = smooth_plan(x, v.triangles, v.body, v.free_edge, **kw)
        # room for 50 % more candidate pairs, and 25 % more grid lines per triangle (w
        # grid and edges change with the state), before the metric functions compile again
        self.capacity = int(np.ceil(1.5 * plan.cand_node.shape[0] / 1024) * 1024)
        self.w_band = int(np.ceil(1.25 * plan.w_band)) + 1
        self.compiles += 1
        return smooth_plan(x, v.triangles, v.body, v.free_edge, capacity=self.capacity,
                           w_band=self.w_band, **kw)

    # ------------------------------------------------------------------ forward
    def feasible(self, rab) -> str:
        """'' when (r, a, b) is a valid template inside the bounds, else the reason."""
        rab = np.asarray(rab, float)
        if np.any(rab < self.objective.lower - 1e-12) or np.any(rab > self.objective.upper + 1e-12):
            return f"(r, a, b) = {tuple(rab)} outside the bounds {self.objective.bounds}"
        try:
            Template(*rab, self.scene.alpha)
        except ParameterError as e:
            return str(e)
        th = self.theta(rab)
        s = self.objective.slacks(th, self.scene.alpha, self._dcc_jit(th))
        bad = [f"{k} slack {float(v):.3f} mm" for k, v in s.items() if float(v) <= 0]
        return "infeasible template: " + ", ".join(bad) if bad else ""

    def forward(self, rab, warm: Evaluation | None = None, *, material=None) -> Evaluation:
        """Close the valve(s) for (r, a, b) mm and evaluate the objective.  material: a
        material of the scene's law with other moduli (e.g. a stiffness sample); its
        values are traced, so nothing recompiles.  `gradient` and `sensitivities` are
        taken at the scene's own material."""
        rab = np.asarray(rab, float)
        why = self.feasible(rab)
        if why:
            raise ParameterError(why)
        if material is not None:
            if type(material) is not type(self.material):
                raise ParameterError(f"material must be a {type(self.material).__name__} "
                                     f"(the scene's law); got {type(material).__name__}")
            material.validate()
        th = self.theta(rab)
        if self.design.tmap.needs_remesh(*np.asarray(th), min_angle=self.min_angle):
            self._build(rab)
            warm = None
        if (isinstance(warm, Evaluation) and warm.generation != self.generation
                or not self.warm_start):
            warm = None
        states, plans, solves, metrics = {}, {}, [], {}
        for load in self.loads:
            p_from = 0.0           # the closure's start is an equilibrium at p_from mmHg
            if isinstance(warm, dict):                 # {load: x (N, 3)}, e.g. a checkpoint
                seed = warm[load]
            elif warm is not None:
                seed = warm.states[load][1].x
            elif states:
                # in turn, as `simulate` closes: 80 mmHg from the 3 mmHg equilibrium
                seed, p_from = states[LOAD_ORDER[0]][1].x, self.pressure[LOAD_ORDER[0]]
            else:
                seed = self.valve.x_start
            x0 = self._x_fixed_jit(th, jnp.asarray(seed))
            if seed is not self.valve.x_start and not min_distance(
                    self.valve.contact_topology, self._ref_jit(th), x0) > 0.5 * float(
                        self.contact.dhat):
                # an earlier state moved to this template has pairs that (nearly) touch:
                # the barrier closes from apart only, so start from the placement
                seed, p_from = self.valve.x_start, 0.0
                x0 = self._x_fixed_jit(th, jnp.asarray(seed))
            mat = self.material if material is None else material
            if mat.limit_free() is not mat:
                # a start past the law's stretch limit (Gent): the design's placement
                # settled at 0 mmHg, as the closure driver starts `simulate`
                x0n = np.asarray(x0)
                y = admissible_start(self.design_valve(rab), self.scene, x0n,
                                     material=mat, say=self.say)
                if y is not x0n:
                    x0, p_from = jnp.asarray(y), 0.0
            if not p_from < self.pressure[load]:
                p_from = 0.0           # an equilibrium at this load already: no ramp from it
            ls = close_load(self.valve, self.scene, self.pressure[load], x0, p_from=p_from,
                            material=mat, ref=self._ref_jit(th))
            sol, rep = ls.solution, ls.report
            x = np.asarray(sol.x)
            ok = rep.converged and bool(np.all(np.isfinite(x)))
            solves.append(dict(load=load, pressure=self.pressure[load], converged=ok,
                               result=rep.result, steps=rep.steps, residual=rep.residual,
                               seconds=rep.wall_s))
            if not ok:
                reason = f"closure at {self.pressure[load]:g} mmHg: {rep.describe()}"
                if rep.cause:
                    solves[-1]["cause"] = rep.cause
                return Evaluation(rab, self.generation, states, plans, metrics, {},
                                  float("inf"), float("nan"), tuple(solves), False, reason)
            states[load] = (x0, sol)
            plans[load] = self._plan(x)
        # the metrics, the objective and its partial derivatives at fixed states: one
        # program (the backward pass costs about as much as the metrics themselves)
        xs = {l: states[l][1].x for l in self.loads}
        starts = {l: (states[l][0], None) for l in self.loads}   # the direct path's x0 only
        (_, (terms, m)), (g, gx) = self._direct_jit(jnp.asarray(rab), xs, starts, plans,
                                                    jnp.asarray(self.area_ref))
        metrics = {k: float(m[k]) for k in METRICS if k in m}       # METRICS order
        terms = {k: float(v) for k, v in terms.items()}
        d_cc = float(self._dcc_jit(th))
        metrics["area"] = Template(*rab, self.scene.alpha).area
        value = float(sum(terms.values()))
        reason = "" if np.isfinite(value) else f"the objective is not finite: {terms}"
        return Evaluation(rab, self.generation, states, plans, metrics, terms, value, d_cc,
                          tuple(solves), bool(np.isfinite(value)), reason, (g, gx))

    def result(self, ev: Evaluation, *, throw: bool = True):
        """The exact (non-smooth) coaptation of a converged evaluation, as the
        `jaxvalve.simulation.SimulationResult` that `simulate` returns for this design:
        the leaflet mesh mapped to ev's template, the closed states of ``ev``, and a
        closure warm-started from the other load for a load the objective did not need.
        Plots (``plot_profiles``, ``plot_valve``) and ``summary()`` work on it."""
        from jaxvalve.simulation import SimulationResult, SolveReport, measure

        if not ev.converged:
            raise ConvergenceError(f"no result at (r, a, b) = {tuple(ev.rab)}: {ev.reason}")
        if ev.generation != self.generation:
            raise ParameterError("this evaluation belongs to an earlier mesh generation")
        th = self.theta(ev.rab)
        tpl = Template(*np.asarray(ev.rab, float), self.scene.alpha)
        valve = self.design_valve(ev.rab)
        xs, reports = {}, {}
        for s in ev.solves:
            xs[s["load"]] = np.asarray(ev.states[s["load"]][1].x)
            reports[s["load"]] = SolveReport(s["pressure"], s["result"], s["converged"],
                                             s["steps"], s["residual"], s["seconds"], 0.0)
        for load in LOAD_ORDER:
            if load in xs:
                continue
            seed = next(iter(xs.values()))
            ls = close_load(self.valve, self.scene, self.pressure[load],
                            self._x_fixed_jit(th, jnp.asarray(seed)), material=self.material,
                            ref=self._ref_jit(th))
            if throw and not ls.converged:
                raise ConvergenceError(f"closure at {self.pressure[load]:g} mmHg did not "
                                       f"converge: {ls.report.describe()}", ls.solution)
            xs[load] = ls.x
            reports[load] = ls.report
        t0 = time.perf_counter()
        m_he, m = (measure(valve, xs[l], self.scene.g_c) for l in LOAD_ORDER)
        t_m = time.perf_counter() - t0
        return SimulationResult(
            scene=self.scene.replace(r=tpl.r, a=tpl.a, b=tpl.b), valve=valve, x=xs["closed"],
            x_he=xs["he"], metrics=m, metrics_he=m_he, solves=(reports["he"], reports["closed"]),
            timings=dict(setup=0.0, metrics=t_m))

    def design_valve(self, rab):
        """The valve of template (r, a, b) mm on this generation's mesh: the mapped
        leaflet (reference, three times) and its placement."""
        th = self.theta(rab)
        tpl = Template(*np.asarray(rab, float), self.scene.alpha)
        ref = np.asarray(self._ref_jit(th))
        lm = dataclasses.replace(self.valve.leaflet, template=tpl,
                                 points=ref[: self.valve.nodes_per_leaflet])
        x_fix = np.asarray(self._x_fixed_jit(th))
        return dataclasses.replace(self.valve, leaflet=lm, ref=ref, x_placed=x_fix,
                                   x_start=x_fix)

    @property
    def area_ref(self):
        a = self.objective.area_ref
        return Template(self.scene.r, self.scene.a, self.scene.b, self.scene.alpha).area \
            if a is None else a

    # ------------------------------------------------------------------ gradient
    def _terms(self, rab, xs, states, plans, area_ref):
        """The objective from the closed states held fixed on free nodes, the template's
        sutured positions on fixed nodes (the states' own dependence on (r, a, b) enters
        through the adjoint, `gradient`)."""
        th = self._theta_traced(rab)
        metrics = {}
        fixed = self.valve.problem.fixed[:, None]
        for load in self.loads:
            x0, _ = states[load]
            x0 = self.design.x_fixed(th, x_free=x0)
            x = jnp.where(fixed, x0, xs[load])
            m = smooth_metrics(x, plans[load], self.eps)
            for name, (ld, key, fac, _, _) in METRICS.items():
                if ld == load:
                    metrics[name] = fac * m[key]
        terms = self.objective.terms(th, self.scene.alpha, metrics, self.d_cc(th), area_ref)
        return sum(terms.values()), (terms, metrics)

    def _placed(self, rab, x):
        """The reference nodes of template (r, a, b) and x with its sutured nodes placed."""
        th = self._theta_traced(rab)
        return self.design.ref(th), self.design.x_fixed(th, x_free=x)

    def _design_pullback(self, rab, x, g_ref, g_x):
        """d/d(r, a, b) (3,) of <g_ref, ref(r, a, b)> + <g_x, x with sutured nodes placed>."""
        return jax.vjp(lambda q: self._placed(q, x), rab)[1]((g_ref, g_x))[0]

    def pullback(self, rab, load, x, pairs, mu, wrt_params=False, params=None):
        """d/d(r, a, b) (3,) of <mu, R(x with the template's sutured nodes, params(r, a,
        b))> at a closed state x of template (r, a, b) (its sutured nodes already where the
        template puts them); with ``wrt_params`` also its derivative with respect to the
        `Params` (read its material moduli, thickness, pressure).  The residual's VJP is
        `adjoint.residual_vjp`, with the arguments of the adjoint's K^T products, so the
        program the adjoint solve compiled serves; only the template's part (reference
        nodes and sutured positions) compiles here.  params: the load's `Params` at
        (r, a, b) when the caller has them (the adjoint's), else built here."""
        if params is None:
            params = self.base[load].replace(ref=self._ref_jit(self.theta(rab)))
        gx, gp = residual_vjp(jnp.asarray(x), self.valve.problem, params, pairs, mu)
        g = self._design_pull_jit(rab, x, gp.ref, gx)
        return (g, gp) if wrt_params else g

    def _load_metrics(self, rab, load, x, plan):
        """The smooth metrics of one load, (k,) in METRICS order, with the sutured nodes at
        the template's positions (their direct dependence on (r, a, b))."""
        th = self._theta_traced(rab)
        m = smooth_metrics(self.design.x_fixed(th, x_free=x), plan, self.eps)
        return jnp.stack([fac * m[key] for name, (ld, key, fac, _, _) in METRICS.items()
                          if ld == load])

    def sensitivities(self, ev: Evaluation) -> dict:
        """Derivatives of the smooth metrics at a converged evaluation: {metric: {param:
        d metric / d param}} for every metric of the closed loads, with param r, a, b (mm)
        and the material's moduli (e.g. E, nu for StVK; MPa^-1 for a modulus).  One LU
        adjoint solve per metric (`jaxvalve.solvers.adjoint.solve_lu`, one factorisation
        per closure for all of them); raises
        `ConvergenceError` when ``ev`` did not converge or an adjoint solve failed."""
        if not ev.converged:
            raise ConvergenceError(f"no sensitivities at (r, a, b) = {tuple(ev.rab)}: "
                                   f"{ev.reason}")
        if ev.generation != self.generation:
            raise ParameterError("this evaluation belongs to an earlier mesh generation")
        rab = jnp.asarray(ev.rab)
        th = self.theta(ev.rab)
        out = {}
        for load in self.loads:
            names = [n for n, (ld, *_rest) in METRICS.items() if ld == load]
            x0, sol = ev.states[load]
            J_rab, J_x = self._metric_jac_jit(rab, load, sol.x, ev.plans[load])
            params = self.base[load].replace(ref=self._ref_jit(th))
            # one assembly and factorisation for every metric of this load
            pairs = fixed_pairs(sol)
            mus, _ = solve_lu(self.valve.problem, params, sol.x, pairs,
                              np.asarray(J_x)[:len(names)])
            for k, name in enumerate(names):
                mu = jnp.asarray(mus[k])
                g_rab, gp = self.pullback(rab, load, sol.x, pairs, mu, True, params)
                g = np.asarray(J_rab[k]) + np.asarray(g_rab)
                d = dict(r=float(g[0]), a=float(g[1]), b=float(g[2]))
                for f in dataclasses.fields(gp.material):
                    v = getattr(gp.material, f.name)
                    if v is not None and np.ndim(v) == 0:
                        d[f.name] = float(v)
                out[name] = d
        return out

    def gradient(self, ev: Evaluation):
        """(value, grad (3,), info) of the objective at a converged evaluation: the
        partial derivatives at fixed states plus, per closure, one adjoint solve
        K^T mu = df/dx (`jaxvalve.solvers.adjoint.solve_lu`, the exact tangent's LU)
        pulled back to (r, a, b).  info: {'adjoint': [AdjointReport per closure]}.
        Raises `ConvergenceError` when ``ev`` did not converge (no adjoint of a
        non-equilibrium) or an adjoint solve missed its tolerance."""
        if not ev.converged:
            raise ConvergenceError(f"no gradient at (r, a, b) = {tuple(ev.rab)}: {ev.reason}")
        if ev.generation != self.generation:
            raise ParameterError("this evaluation belongs to an earlier mesh generation")
        rab = jnp.asarray(ev.rab)
        v, (g, gx) = ev.value, ev.partials        # from the forward evaluation's program
        g = np.asarray(g)
        reports = []
        th = self.theta(ev.rab)
        for load in self.loads:
            x0, sol = ev.states[load]
            params = self.base[load].replace(ref=self._ref_jit(th))
            pairs = fixed_pairs(sol)
            mu, rep = solve_lu(self.valve.problem, params, sol.x, pairs, gx[load])
            reports.append(rep)
            g = g + np.asarray(self.pullback(rab, load, sol.x, pairs, jnp.asarray(mu),
                                             params=params))
        return float(v), g, {"adjoint": reports}
