"""`simulate_batch(scene, materials)`: one valve closed under many materials at once.

The valve (root, mesh, placement) is built once.  Every member of the batch is a material
of one model (one pytree structure: `StVenantKirchhoff`, `NeoHookean`, `Gent` or
`MassSpring` with the same fields set).  Each load is closed for all members by the
engine's FIRE phase under `jax.vmap`, in ONE compiled program (`jaxvalve.solvers.
equilibrium.fire_batch`): every material float is a traced input, so a second batch of the
same size and model does not recompile, and the pair lists are built and kept inside it,
per member.  The loop runs until every member has finished, a finished member keeping its
state; the pair-list refreshes and FIRE's mass refreshes run once for the batch where any
member needs them (`jaxvalve.unvmap`), and every member takes the refreshed lists
(`jaxvalve.contact.pairs.update`): a member's trajectory then depends on its companions
within the solver's tolerance, not beyond it.

Members are then finished in turn, on the host, by the one closure driver
(`jaxvalve.valve.closure.close_valve`, with the batched solves as its first attempts):
where a member's FIRE stagnated, the Newton finish from its best state (a sparse LU on the
host: one factorisation at a time serves a CPU as well as a GPU would, and it is needed by
few members), the state check, and continuation in pressure for a member that ran away,
so that a member's report is `simulate`'s.  The sharp coaptation metrics are measured per
member on the host (NumPy), as `simulate` does.  Members whose pair lists overflowed the
batch's capacities are closed again alone, where `equilibrium.solve` grows them.
"""
from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from .contact import pairs as pair_lists
from .solvers.equilibrium import MARGIN, SKIN, contact_args, finish, fire_batch
from .errors import ConvergenceError, ParameterError
from .mechanics.materials import Material
from .mechanics.problem import mmhg, validate_params
from .scene import Scene
from .valve import model as V
from .simulation import _quiet, build_scene_valve, measure
from .timing import compile_timer
from .valve.closure import admissible_start, close_valve
from .solvers import RESULTS, Solution, Stats

__all__ = ["simulate_batch", "BatchResult", "BatchMember", "stack_materials", "METRICS"]

#: The headline metrics of a member (keys of `BatchMember.summary`), mm and %.
METRICS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")


# ------------------------------------------------------------------------------ materials
def _fields(mat) -> list[str]:
    """The data (traced) fields of a material dataclass, in declaration order."""
    return [f.name for f in dataclasses.fields(mat) if not f.metadata.get("static")]


def stack_materials(materials, template: Material | None = None):
    """(members, stacked): the batch as a list of validated `Material` objects of one
    model, and the same stacked into one material whose float leaves have shape (B,).

    materials: a sequence of materials of one model with the same fields set, or a dict
    {field: sequence of B values} applied to ``template`` (the other fields are the
    template's).  Raises `ParameterError` naming the member and the parameter."""
    if isinstance(materials, Mapping):
        if template is None:
            raise ParameterError("materials given as a dict need a template material "
                                 "(the scene's model)")
        names = _fields(template)
        unknown = sorted(set(materials) - set(names))
        if unknown:
            raise ParameterError(f"materials: unknown parameters {unknown} for the "
                                 f"{template.name} model; valid: {names}")
        if not materials:
            raise ParameterError("materials: the dict is empty; give at least one parameter "
                                 "with one value per member")
        cols = {}
        for k, v in materials.items():
            try:
                a = np.asarray(v, dtype=float)
            except (TypeError, ValueError):
                raise ParameterError(f"materials[{k!r}] must be numbers (one per member); "
                                     f"got {v!r}") from None
            if a.ndim != 1 or a.size == 0:
                raise ParameterError(f"materials[{k!r}] must be a non-empty 1-D sequence of "
                                     f"values (one per member); got shape {a.shape}")
            cols[k] = a
        sizes = {k: a.size for k, a in cols.items()}
        if len(set(sizes.values())) != 1:
            raise ParameterError(f"materials: every parameter needs the same number of "
                                 f"values (one per member); got {sizes}")
        n = next(iter(sizes.values()))
        members = [dataclasses.replace(template, **{k: float(a[i]) for k, a in cols.items()})
                   for i in range(n)]
    else:
        if isinstance(materials, Material):
            materials = [materials]
        try:
            members = list(materials)
        except TypeError:
            raise ParameterError("materials must be a sequence of material objects of one "
                                 "model or a dict {parameter: values}; got "
                                 f"{type(materials).__name__}") from None
    if not members:
        raise ParameterError("materials is empty; the batch needs at least one member")
    for i, m in enumerate(members):
        if not isinstance(m, Material):
            raise ParameterError(f"materials[{i}] is a {type(m).__name__}, not a material "
                                 "(jaxvalve.mechanics.materials: StVenantKirchhoff, "
                                 "NeoHookean, Gent, MassSpring)")
    kind, tree0 = type(members[0]), jax.tree_util.tree_structure(members[0])
    for i, m in enumerate(members):
        if type(m) is not kind or jax.tree_util.tree_structure(m) != tree0:
            raise ParameterError(
                f"materials[{i}] ({type(m).__name__}) differs in model or in the fields set "
                f"from materials[0] ({kind.__name__}): a batch holds one model with the same "
                "fields (run one batch per model)")
        try:
            m.validate()
        except ParameterError as e:
            raise ParameterError(f"materials[{i}]: {e}") from None
        for leaf in jax.tree_util.tree_leaves(m):
            if np.ndim(leaf) != 0:
                raise ParameterError(f"materials[{i}]: every parameter must be a scalar; got "
                                     f"shape {np.shape(leaf)}")
    stacked = jax.tree_util.tree_map(
        lambda *v: jnp.asarray(np.asarray(v, dtype=np.float64)), *members)
    return members, stacked


def _parameters(mat) -> dict:
    """{field: float} of the fields that are set (None fields left out)."""
    return {k: float(getattr(mat, k)) for k in _fields(mat) if getattr(mat, k) is not None}


# ------------------------------------------------------------------------------ results
@dataclasses.dataclass(frozen=True)
class BatchMember:
    """One member of a batch: its material, closed states, metrics and solve reports.

    x, x_he (N, 3) mm: closed at ``pressure`` and at ``he_pressure``.  metrics,
    metrics_he: `CoaptationResult` (None where the state is not finite).
    solves: (`SolveReport` at he_pressure, `SolveReport` at pressure), as `simulate`'s
    (their wall times count only a member's own continuation solves, not the batch)."""

    index: int
    model: str
    material: Material
    x: np.ndarray
    x_he: np.ndarray
    metrics: Any
    metrics_he: Any
    solves: tuple

    @property
    def parameters(self) -> dict:
        return _parameters(self.material)

    @property
    def converged(self) -> bool:
        return all(s.converged for s in self.solves)

    @property
    def measured(self) -> bool:
        return self.metrics is not None and self.metrics_he is not None

    def summary(self) -> dict:
        """The headline metrics (mm, %), as `SimulationResult.summary`.  NaN for a member
        whose state is not finite (it is then not converged; see ``converged``)."""
        if not self.measured:
            return {k: math.nan for k in METRICS + ("coaptation_area",)}
        m = self.metrics
        return dict(h_E=self.metrics_he.h_e, h_CC=m.h_cc, h_avr=m.h_avr_valve,
                    NCCA_pct=100 * m.ncca_valve, h=m.h, h_c=m.h_c,
                    coaptation_area=float(np.sum(m.zone_area)))

    def describe(self) -> str:
        p = ", ".join(f"{k}={v:g}" for k, v in self.parameters.items())
        s = "; ".join(f"{r.pressure:g} mmHg: {r.describe()}" for r in self.solves)
        return f"member {self.index} ({self.model}: {p}): {s}"


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """A batch of closures of one valve.

    scene: the `Scene` (geometry, loads, solver; its material fields are not used).
    valve: the `Valve`.  model: the materials' model name.  members: `BatchMember` each.
    timings (s): 'setup' (root, mesh, placement; 0 with a prebuilt valve), 'compile' and
    'solve' (the batched calls and the members' own finishes and continuation solves:
    JAX's compile time and the rest of their wall time), 'batched' (the batched calls'
    part of 'solve'), 'follow_up' (the part spent after them, on members' own Newton
    finishes and continuation solves), 'metrics' (host: the state checks and coaptation
    metrics), 'total', 'per_scene' (solve / members)."""

    scene: Scene
    valve: Any
    model: str
    members: tuple
    timings: dict

    def __len__(self):
        return len(self.members)

    def __getitem__(self, i) -> BatchMember:
        return self.members[i]

    def __iter__(self):
        return iter(self.members)

    @property
    def converged(self) -> bool:
        return all(m.converged for m in self.members)

    @property
    def failed(self) -> list[int]:
        """Indices of the members that did not converge (at either load)."""
        return [m.index for m in self.members if not m.converged]

    def summaries(self) -> list[dict]:
        return [m.summary() for m in self.members]

    def rows(self) -> list[dict]:
        """One flat dict per member: model, parameters, every metric, converged, and per
        load the result, steps, Newton steps, residual, the cause of a failure and the
        limit pressure (mmHg, None but at a limit point) (the CSV of `jaxvalve sweep`)."""
        out = []
        for m in self.members:
            r = dict(member=m.index, model=m.model, **m.parameters, **m.summary(),
                     converged=m.converged)
            for tag, s in zip(("he", "closing"), m.solves):
                r.update({f"result_{tag}": s.result, f"steps_{tag}": s.steps,
                          f"newton_{tag}": s.newton_steps, f"residual_{tag}": s.residual,
                          f"cause_{tag}": s.cause or "",
                          f"limit_pressure_{tag}": s.limit_pressure})
            out.append(r)
        return out


# ------------------------------------------------------------------------------ the solve
def _batched_load(valve, scene, members, stacked, base, x0s, p_mmhg, caps):
    """One load for all members: the engine's FIRE phase under vmap (run again with grown
    capacities where a member's pair lists overflowed), then per member the Newton finish
    where FIRE stagnated.  Returns (state-checked `ValveSolution` per member, batched
    seconds, compile seconds of the batched call, the capacities it ended with)."""
    solver = scene.make_solver()
    params = jax.tree_util.tree_map(
        lambda a: jnp.broadcast_to(a, (len(members),) + jnp.shape(a)),
        base.replace(pressure=mmhg(p_mmhg), material=None))
    params = params.replace(material=stacked)
    with compile_timer() as ct:
        t0 = time.perf_counter()
        for _ in range(8):
            out = fire_batch(valve.problem, params, jnp.asarray(x0s), solver,
                             valve.contact_topology, caps)
            jax.block_until_ready(out)
            y, result, steps, res, best, rbest, over, c_need, a_need, raw = (
                np.asarray(a) for a in out)
            if not over.any():
                break
            # as `equilibrium.solve` does: grow the capacities past the largest need of
            # any member, and run the batch again
            caps = caps.grown(c_need.max(0), a_need.max(0), raw.max(0))
        wall = time.perf_counter() - t0
    sols = []
    for i, mat in enumerate(members):
        p_i = base.replace(pressure=mmhg(p_mmhg), material=mat)
        if over[i]:
            sols.append(None)       # the driver closes it again, alone
            continue
        stats = Stats(steps=jnp.asarray(steps[i]), force_evals=jnp.asarray(steps[i]),
                      hvps=jnp.asarray(0), residual=jnp.asarray(res[i]))
        sol = Solution(x=jnp.asarray(y[i]), result=jnp.asarray(result[i]), stats=stats,
                       caps=caps, topo=valve.contact_topology)
        if int(result[i]) in (RESULTS.stagnation, RESULTS.max_steps_reached):
            _, extra = contact_args(valve.problem, p_i, jnp.asarray(best[i]),
                                    valve.contact_topology, caps)
            sol = dataclasses.replace(sol, lists=extra["lists"])
            sol = finish(valve.problem, p_i, solver, sol, jnp.asarray(best[i]), rbest[i])
        sols.append(V.checked(valve, sol, self_contact=True))
    return sols, wall, min(ct.seconds, wall), caps


def _member_say(say, i):
    """Progress of member i's continuation solves (the driver reports only those)."""
    return lambda msg: say(f"  member {i}: {msg.strip()}")


def simulate_batch(scene: Scene | None = None, materials=None, *, valve=None,
                   progress: Callable[[str], None] | None = None,
                   throw: bool = True) -> BatchResult:
    """Close the valve of ``scene`` under every material of ``materials`` (one batch).

    scene: geometry (root, template, h), loads (he_pressure, pressure), thickness, fibre
    angle, bending, rtol, max_steps and g_c; default the benchmark `Scene()`.  Its
    material fields are not used, except as the template of a dict.
    materials: a sequence of materials of one model with the same fields set (e.g.
    ``[StVenantKirchhoff(E=e, nu=0.45) for e in (0.5, 1, 2)]``), or a dict
    ``{parameter: values}`` over ``scene.material()`` (e.g. ``{"E1": [...], "E2":
    [...]}`` with a mass-spring scene); default the scene's material alone.
    valve: a prebuilt `Valve` of this scene's root and template (skips the setup).
    progress: called with one line of text per phase.
    throw: raise `ConvergenceError` naming the members that did not converge (its
    ``solution`` is the `BatchResult`); with throw=False the result is returned and
    ``result.failed`` lists them, each with its residual in ``member.solves``."""
    scene = Scene() if scene is None else scene
    if scene.solver != "engine":
        raise ParameterError(f"simulate_batch closes valves with the engine "
                             f"(scene.solver='engine'); got solver={scene.solver!r}")
    say = progress or _quiet
    t_all = time.perf_counter()
    template = scene.material() if materials is None or isinstance(materials, Mapping) else None
    members, stacked = stack_materials(template if materials is None else materials,
                                       template=template)
    model = members[0].name
    t0 = time.perf_counter()
    valve = build_scene_valve(scene, say) if valve is None else valve
    setup = time.perf_counter() - t0
    x0 = jnp.asarray(valve.x_start, scene.dtype)
    base = valve.params(members[0], scene.he_pressure, scene.contact_law(), scene.thickness,
                        np.deg2rad(scene.fibre_angle), scene.bending_law())
    validate_params(base)
    # each member's start inside its stretch limit (`admissible_start`), found before the
    # batched program runs, so that a member past the limit even at rest is refused
    # (ParameterError) before any expensive work
    placed = np.asarray(valve.x_start)
    starts = np.stack([admissible_start(valve, scene, placed, material=mat)
                       for mat in members])
    base = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), base)
    stacked = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), stacked)
    B = len(members)
    say(f"closing {B} member{'s' * (B != 1)} ({model}) at {scene.he_pressure:g} then "
        f"{scene.pressure:g} mmHg in one batch (engine)")
    # the contact's settings checked against the valve before any expensive work, and
    # capacities for the closed valve (`Capacities.for_mesh`)
    contact_args(valve.problem, base.replace(material=members[0]), x0, valve.contact_topology)
    caps = pair_lists.Capacities.for_mesh(valve.contact_topology, base.contact.dhat, SKIN,
                                          MARGIN)
    stages, batched_s, compile_s = [], 0.0, 0.0
    x_from = starts
    for p in (scene.he_pressure, scene.pressure):
        sols, wall, comp, caps = _batched_load(valve, scene, members, stacked, base,
                                               x_from, p, caps)
        stages.append(sols)
        batched_s += wall
        compile_s += comp
        x_from = np.stack([np.asarray(s.x) if s is not None else x_from[i]
                           for i, s in enumerate(sols)])
        n_ok = sum(s is not None and s.converged for s in sols)
        say(f"  {p:g} mmHg: {n_ok}/{B} converged in the batch and its Newton finishes; "
            f"{max(wall - comp, 0.0):.2f} s (+{comp:.1f} s compile)")
    t_driver, c_driver = 0.0, 0.0
    t0 = time.perf_counter()
    out = []
    for i, mat in enumerate(members):
        first = tuple(st[i] for st in stages)
        if first[0] is None:
            first = ()
        elif first[1] is None:
            first = first[:1]
        loads = close_valve(valve, scene, material=mat, first=first, x0=starts[i],
                            say=_member_say(say, i))
        own = sum(ls.report.wall_s for ls in loads if ls.report.wall_s > 0)
        t_driver += own
        c_driver += sum(ls.report.compile_s for ls in loads)
        xs = [ls.x for ls in loads]
        finite = [bool(np.all(np.isfinite(x))) for x in xs]
        say(f"measuring coaptation: member {i + 1}/{B}")
        m_he = measure(valve, xs[0], scene.g_c) if finite[0] else None
        m = measure(valve, xs[1], scene.g_c) if finite[1] else None
        out.append(BatchMember(index=i, model=model, material=mat, x=xs[1], x_he=xs[0],
                               metrics=m, metrics_he=m_he,
                               solves=tuple(ls.report for ls in loads)))
    compile_s += c_driver
    solve_s = max(batched_s + t_driver - compile_s, 0.0)
    say(f"  {sum(m.converged for m in out)}/{B} converged; {solve_s:.2f} s "
        f"(+{compile_s:.1f} s compile), {solve_s / B:.2f} s a member")
    t_m = time.perf_counter() - t0 - t_driver
    timings = dict(setup=setup, compile=compile_s, solve=solve_s, batched=batched_s,
                   metrics=t_m, follow_up=max(t_driver - c_driver, 0.0),
                   total=time.perf_counter() - t_all, per_scene=solve_s / B)
    res = BatchResult(scene=scene, valve=valve, model=model, members=tuple(out),
                      timings=timings)
    if throw and not res.converged:
        bad = [res.members[i] for i in res.failed]
        raise ConvergenceError(
            f"{len(bad)} of {B} members did not converge (rtol {scene.rtol:g}): "
            + "; ".join(m.describe() for m in bad), res)
    return res
