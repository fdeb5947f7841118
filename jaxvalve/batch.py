"""`simulate_batch(scene, materials)`: one valve closed under many materials at once.

The valve (root, mesh, placement) is built once.  Every member of the batch is a material
of one model (one pytree structure: `StVenantKirchhoff`, `NeoHookean`, `Gent` or
`MassSpring` with the same fields set).  The two closures of `simulate` (at
``scene.he_pressure`` from the valve's start, then at ``scene.pressure`` from that state)
run for all members under `jax.vmap`, inside ONE `jax.jit`; every material float is a
traced input, so a second batch of the same size and model does not recompile.  Each
member's outcome then goes through the one closure driver (`jaxvalve.valve.closure.close_valve`,
with the batched solves as its first attempts): the state check, continuation in pressure
for a member that ran away, the stall probe for one stopped at its step cap, so that a
member's report is `simulate`'s.  The sharp coaptation metrics are measured per member on
the host (NumPy), as `simulate` does.  On the barrier path (a host-loop Newton solver)
there is no batched program: the driver closes the members one after the other.

The solver loop (`lax.while_loop` under vmap) runs until every member has finished and
keeps a finished member's state.  The decisions inside it (pair-list rebuilds, the contact
energy's prefix length, FIRE's mass refresh) are taken per member but computed only for
the members that need them (`jaxvalve.vmap_control`).  Two ways to run the steps:

* ``vectorize=False`` (default on CPU): each member runs its own solver loop, one after
  the other (`iterate(members_apart=True)`), the compiled loop of a single solve.  A
  member's result is then `simulate`'s to the last bit, whatever the batch (tested), and
  finished members cost nothing.
* ``vectorize=True`` (default on GPU): the steps of all members are one array program,
  and so are the rebuilds (`vmap_control.branches("select")`: run for the whole batch when any
  member is due, each member keeping its own branch), so a step's cost hardly grows with
  the batch on a GPU.  Once few members are left (``handoff``, default max(1, B // 16)),
  each of them finishes in its own single-solve loop, so a straggler does not pay a
  batch's step to the end.  XLA orders a few sums differently for batched arrays, so members
  differ from sequential runs by rounding (1e-16), which FIRE's path can amplify to ~1e-3
  mm at rtol 1e-4 (the size of the path dependence of the closed state; docs/batch.md).
  On a 2-core CPU it is slower than the member loop (`benchmarks/batch.py`).

A batch of one member runs the unbatched program of a single solve (no vmap) either way.

Contact pair lists have static capacities.  Members whose list overflowed (result
``neighbour_overflow``) are solved again, alone, at a larger capacity, as
`equilibrium.solve` does for one solve.
"""
from __future__ import annotations

import dataclasses
import functools
import math
import time
from typing import Any, Callable, Mapping

import jax
import jax.numpy as jnp
import numpy as np

from . import contact as _contact
from .vmap_control import branches
from .contact.neighbours import DEFAULT_SCAN_RATIO, MAX_GROUP
from .contact.soft_pairs import SoftPairs, stale_soft_pairs
from .solvers.equilibrium import (_fill, _make_args, _setting_args, contact_cutoff, stale_pairs,
                                  update_pairs)
from .errors import ConvergenceError, ParameterError
from .mechanics.materials import Material
from .mechanics.problem import mmhg, validate_params
from .scene import Scene
from .valve import model as V
from .simulation import _quiet, build_scene_valve, measure
from .timing import compile_timer
from .valve.closure import admissible_start, close_valve
from .solvers import RESULTS, Solution, Stats, iterate
from .solvers.base import relative_residual

__all__ = ["simulate_batch", "BatchResult", "BatchMember", "stack_materials", "METRICS"]

#: The headline metrics of a member (keys of `BatchMember.summary`), mm and %.
METRICS = ("h_E", "h_CC", "h_avr", "NCCA_pct", "h", "h_c")

_MAX_RETRIES = 6


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
        s = "; ".join(f"{r.pressure:g} mmHg: {r.result}, residual {r.residual:.3e} after "
                      f"{r.steps} steps" + (f" ({r.cause})" if r.cause else "")
                      + (f" [{r.path}, after {r.fallback}]" if r.fallback else "")
                      for r in self.solves)
        return f"member {self.index} ({self.model}: {p}): {s}"


@dataclasses.dataclass(frozen=True)
class BatchResult:
    """A batch of closures of one valve.

    scene: the `Scene` (geometry, loads, solver; its material fields are not used).
    valve: the `Valve`.  model: the materials' model name.  members: `BatchMember` each.
    timings (s): 'setup' (root, mesh, placement; 0 with a prebuilt valve), 'compile' and
    'solve' (the batched call and the members' own continuation or barrier solves: JAX's
    compile time and the rest of their wall time), 'follow_up' (the part of 'solve' spent
    after the batched call, on members' own continuation or barrier solves), 'metrics'
    (host: the state checks, stall probes and coaptation metrics), 'total', 'per_scene'
    (solve / members), 'retries' (capacity retries of overflowing members).  vectorized: how the steps ran (`simulate_batch`)."""

    scene: Scene
    valve: Any
    model: str
    members: tuple
    timings: dict
    vectorized: bool = False

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
        load the result, steps, residual, stall cause, the path that closed it, the
        failure it fell back after and the limit pressure (mmHg, None but at a limit
        point) (the CSV of `jaxvalve sweep`)."""
        out = []
        for m in self.members:
            r = dict(member=m.index, model=m.model, **m.parameters, **m.summary(),
                     converged=m.converged)
            for tag, s in zip(("he", "closing"), m.solves):
                r.update({f"result_{tag}": s.result, f"steps_{tag}": s.steps,
                          f"residual_{tag}": s.residual, f"cause_{tag}": s.cause or "",
                          f"path_{tag}": s.path or "", f"fallback_{tag}": s.fallback or "",
                          f"limit_pressure_{tag}": s.limit_pressure})
            out.append(r)
        return out


# ------------------------------------------------------------------------------ the solve
def _solve(solver, problem, params, x0, nbrs, skin, loop, handoff=0):
    """`equilibrium._run` (forward only): (x, result, stats, pair list); with ``loop``
    each member runs its own solver loop (`iterate(members_apart=True)`), else the steps
    are vectorised until at most ``handoff`` members run (`iterate(handoff=...)`)."""
    system, args = _make_args(problem, params, x0, nbrs, solver, skin)
    steps = evals = hvps = jnp.asarray(0)
    y = x0
    for warm in getattr(solver, "warm_start", None) or ():
        y, args, st, _, n = iterate(warm, system, y, args, members_apart=loop, beacon=False,
                                    handoff=handoff)
        args = system.update(y, args)
        s = warm.stats(st)
        steps, evals, hvps = steps + n, evals + s["force_evals"], hvps + s["hvps"]
    y, args, st, result, n = iterate(solver, system, y, args, members_apart=loop, beacon=False,
                                     handoff=handoff)
    s = solver.stats(st)
    res = relative_residual(system, y, args, st["F"] if "F" in st else None)
    if getattr(solver, "lazy_force", False):   # no step ran: F(x0) was never evaluated
        res = jnp.where(n > 0, res, jnp.inf)
    stats = Stats(steps=steps + n, force_evals=evals + s["force_evals"],
                  hvps=hvps + s["hvps"], residual=res)
    return y, result, stats, args["nbrs"]


def _member(material, *, solver, problem, base, x0, nbrs, pressures, skin, lazy, loop,
            handoff=0):
    """Both closures of one member (vmapped): pressures[0] from x0, then pressures[1] from
    that state.  A `lax.scan` over the two loads, so the solve is traced and compiled once
    (as `simulate`'s two calls share one compiled solve)."""

    def stage(x, p):
        params = base.replace(material=material, pressure=p)
        nb = nbrs
        if params.contact is not None and not lazy:
            nb = update_pairs(nbrs, x, problem, skin, params.contact)   # built at x
        y, result, stats, nb_out = _solve(solver, problem, params, x, nb, skin, loop,
                                          handoff)
        zero = jnp.asarray(0, jnp.int32)
        ov = dict(base_overflow=jnp.asarray(False), count=zero, n_scan=zero, max_group=zero,
                  soft_overflow=jnp.asarray(False), soft_count=zero)
        if nb_out is not None:
            b = nb_out.base if isinstance(nb_out, SoftPairs) else nb_out
            ov.update(base_overflow=b.overflow, count=b.count, n_scan=b.n_scan,
                      max_group=b.max_group_count)
            if isinstance(nb_out, SoftPairs):
                ov.update(soft_overflow=nb_out.soft_overflow, soft_count=nb_out.soft_count)
        return y, dict(x=y, result=result, steps=stats.steps, residual=stats.residual, **ov)

    _, out = jax.lax.scan(stage, x0, pressures)
    return out


@functools.partial(jax.jit, static_argnames=("solver", "skin", "lazy", "loop", "handoff"))
def _close_batch(materials, problem, base, x0, nbrs, pressures, settings, *, solver, skin,
                 lazy, loop, handoff=0):
    """Both closures of every member.  solver: static, without its traced settings
    (``settings``, `equilibrium.TRACED_SETTINGS`)."""
    solver = _fill(solver, settings)
    f = functools.partial(_member, solver=solver, problem=problem, base=base, x0=x0,
                          nbrs=nbrs, pressures=pressures, skin=skin, lazy=lazy, loop=False)
    if jax.tree_util.tree_leaves(materials)[0].shape[0] == 1:
        # one member: the unbatched program of a single solve (no vmap, no selects)
        one = f(jax.tree_util.tree_map(lambda a: a[0], materials))
        return jax.tree_util.tree_map(lambda a: a[None], one)
    # vectorised: the rebuild branches too run as one array program (`vmap_control.branches`)
    with branches("members" if loop else "select"):
        return jax.vmap(functools.partial(f, loop=loop, handoff=0 if loop else handoff))(
            materials)


def _stale(contact, problem, x0, skin, capacity=None, soft_capacity=None):
    """Empty pair lists (built by each member's first update), at given capacities."""
    if contact is None:
        return None
    if capacity is None and soft_capacity is None:
        return stale_pairs(contact, problem, x0, skin)
    cutoff = contact_cutoff(contact, jnp.asarray(x0), problem.triangles, skin)
    base = _contact.stale_list(problem.n_nodes, problem.triangles, problem.body, cutoff,
                               capacity=capacity, dtype=jnp.asarray(x0).dtype)
    if not getattr(contact, "soft_min", False):
        return base
    return stale_soft_pairs(base, soft_capacity)


def _capacities(nbrs):
    if nbrs is None:
        return None, None
    if isinstance(nbrs, SoftPairs):
        return nbrs.capacity, nbrs.soft_capacity
    return nbrs.capacity, None


def _run_batch(members, stacked, valve, base, pressures, solver, skin, loop, say,
               handoff=0):
    """The batched call, with capacity retries: returns (stages: 2 dicts of (B, ...) NumPy
    arrays, compile_s, wall_s, retries).  Members whose contact pair list overflowed are
    solved again, alone, with grown capacities (as `equilibrium.solve` does), up to
    _MAX_RETRIES times; a member that still overflows, or whose overflow no capacity cures
    (a node with more than MAX_GROUP candidate triangles of one leaflet), keeps its
    ``neighbour_overflow`` result and is reported as not converged."""
    problem = valve.problem
    x0 = jnp.asarray(valve.x_start)
    lazy = getattr((getattr(solver, "warm_start", None) or (solver,))[0], "lazy_force", False)
    nbrs = _stale(base.contact, problem, x0, skin)
    blank, settings = _setting_args(solver, jnp.asarray(x0).dtype)
    B = len(members)
    todo = np.arange(B)
    stages = None
    compile_s = wall_s = 0.0
    retries = 0
    while True:
        sub = stacked if len(todo) == B else jax.tree_util.tree_map(lambda a: a[todo], stacked)
        with compile_timer() as ct:
            t0 = time.perf_counter()
            out = _close_batch(sub, problem, base, x0, nbrs, pressures, settings,
                               solver=blank, skin=float(skin), lazy=bool(lazy), loop=loop,
                               handoff=int(handoff))
            out = jax.device_get(jax.block_until_ready(out))
            wall = time.perf_counter() - t0
        compile_s += min(ct.seconds, wall)
        wall_s += wall
        out = [{k: np.array(np.asarray(v)[:, j]) for k, v in out.items()} for j in range(2)]
        if stages is None:
            stages = out
        else:
            for st, new in zip(stages, out):
                for k in st:
                    st[k][todo] = new[k]
        over = np.zeros(B, bool)
        for st in stages:
            over |= st["result"] == int(RESULTS.neighbour_overflow)
        over[np.setdiff1d(np.arange(B), todo)] = False      # settled in an earlier round
        hopeless = np.zeros(B, bool)
        for st in stages:
            hopeless |= over & (st["max_group"] > MAX_GROUP)
        if hopeless.any():
            say(f"  members {np.flatnonzero(hopeless).tolist()}: a node has more than "
                f"{MAX_GROUP} candidate triangles of one leaflet (a crumpled state); "
                "no pair-list capacity helps, reported as not converged")
        over &= ~hopeless
        if not over.any():
            break
        if retries == _MAX_RETRIES:
            say(f"  members {np.flatnonzero(over).tolist()}: the contact pair list still "
                f"overflowed after {_MAX_RETRIES} retries; reported as not converged")
            break
        todo = np.flatnonzero(over)
        cap, soft_cap = _capacities(nbrs)
        sel = lambda k: max(int(st[k][todo].max()) for st in stages)
        if any(st["base_overflow"][todo].any() for st in stages):
            need = max(sel("count"), -(-sel("n_scan") // DEFAULT_SCAN_RATIO))
            cap = 2 * max(cap, need)
        if soft_cap is not None and any(st["soft_overflow"][todo].any() for st in stages):
            soft_cap = 2 * max(soft_cap, sel("soft_count"))
        say(f"  contact pair list overflowed for members {todo.tolist()}: solving them again "
            f"with capacity {cap}" + (f" / {soft_cap}" if soft_cap is not None else ""))
        nbrs = _stale(base.contact, problem, x0, skin, cap, soft_cap)
        retries += 1
    return stages, compile_s, wall_s, retries


def _first_attempts(valve, stages, i) -> tuple:
    """Member i's first attempt at each load, from the batched program, as state-checked
    `ValveSolution`s (a state that is not finite has result ``nonfinite``)."""
    out = []
    for st in stages:
        x = np.asarray(st["x"][i])
        code = int(st["result"][i]) if np.all(np.isfinite(x)) else int(RESULTS.nonfinite)
        stats = Stats(steps=int(st["steps"][i]), force_evals=0, hvps=0,
                      residual=float(st["residual"][i]))
        out.append(V.checked(valve, Solution(x=x, result=np.asarray(code), stats=stats)))
    return tuple(out)


def _member_say(say, i):
    """Progress of member i's continuation solves (the driver reports only those)."""
    return lambda msg: say(f"  member {i}: {msg.strip()}")


def simulate_batch(scene: Scene | None = None, materials=None, *, valve=None,
                   progress: Callable[[str], None] | None = None, throw: bool = True,
                   vectorize: bool | None = None, handoff: int | None = None) -> BatchResult:
    """Close the valve of ``scene`` under every material of ``materials`` (one batch).

    scene: geometry (root, template, h), loads (he_pressure, pressure), thickness, fibre
    angle, bending, contact, solver, rtol, max_steps and g_c; default the benchmark
    `Scene()`.  Its material fields are not used, except as the template of a dict.
    materials: a sequence of materials of one model with the same fields set (e.g.
    ``[StVenantKirchhoff(E=e, nu=0.45) for e in (0.5, 1, 2)]``), or a dict
    ``{parameter: values}`` over ``scene.material()`` (e.g. ``{"E1": [...], "E2":
    [...]}`` with a mass-spring scene); default the scene's material alone.
    valve: a prebuilt `Valve` of this scene's root and template (skips the setup).
    progress: called with one line of text per phase.
    throw: raise `ConvergenceError` naming the members that did not converge (its
    ``solution`` is the `BatchResult`); with throw=False the result is returned and
    ``result.failed`` lists them, each with its residual in ``member.solves``.
    vectorize: run the solver steps of all members as one vectorised array program (True),
    or each member's solver loop in turn (False: each member then runs the same compiled
    loop as a single `simulate`, so its result is the sequential one to the last bit, and
    finished members cost nothing).  Default: False on CPU, where vectorising does
    not pay, True on GPU.  Vectorised members differ from sequential runs by rounding
    (XLA orders some sums differently), which the solver's path can amplify to ~1e-3 mm
    at rtol 1e-4.
    handoff (vectorised steps only): once at most this many members are still running,
    each of them finishes in its own single-solve loop (`solvers.base.iterate`), so that a
    straggler's last steps cost one member's step instead of the whole batch's.  0: never;
    default max(1, B // 16), from the GPU step costs of `benchmarks/batch.py` (a vectorised
    step of 16 members cost 2-3 single steps, of 64 members 4-7).
    """
    if handoff is not None and (isinstance(handoff, bool) or not isinstance(handoff, int)
                                or handoff < 0):
        raise ParameterError(f"handoff must be an integer >= 0 (members still running when "
                             f"each finishes in its own loop; 0: never); got {handoff!r}")
    scene = Scene() if scene is None else scene
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
    # (ParameterError) before any expensive work; a settled start is handed to the
    # driver, whose batched first attempts (from the placement) it then skips
    placed = np.asarray(valve.x_start)
    starts = [admissible_start(valve, scene, placed, material=mat) for mat in members]
    # strong float64 leaves, as `equilibrium.solve`: one compiled function for any value
    base = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), base)
    stacked = jax.tree_util.tree_map(lambda a: jnp.asarray(a, dtype=x0.dtype), stacked)
    pressures = jnp.asarray([mmhg(scene.he_pressure), mmhg(scene.pressure)], x0.dtype)
    solver = scene.make_solver()
    if vectorize is None:
        vectorize = jax.default_backend() != "cpu"
    loop = not vectorize
    B = len(members)
    handoff = max(1, B // 16) if handoff is None else handoff
    say(f"closing {B} member{'s' * (B != 1)} ({model}) at {scene.he_pressure:g} then "
        f"{scene.pressure:g} mmHg in one batch ({scene.solver} solver, {scene.contact} "
        "contact)")
    if scene.contact == "barrier":
        # the barrier Newton is a host loop (sparse factorisations, CCD on the host): no
        # batched program; each member is closed in turn by the one closure driver
        stages, compile_s, wall_s, retries = None, 0.0, 0.0, 0
    else:
        stages, compile_s, wall_s, retries = _run_batch(members, stacked, valve, base,
                                                        pressures, solver, valve.skin, loop,
                                                        say, handoff=handoff)
        n_ok = int(sum(np.all([st["result"] == RESULTS.successful for st in stages],
                              axis=0)))
        say(f"  {n_ok}/{B} first attempts converged; "
            f"{max(wall_s - compile_s, 0.0):.2f} s (+{compile_s:.1f} s compile)")
    t_driver, c_driver = 0.0, 0.0
    t0 = time.perf_counter()
    out = []
    for i, mat in enumerate(members):
        # the batched program's attempts, finished by the one closure driver: the state
        # check, continuation where a member ran away, the stall probe at a step cap
        settled = starts[i] is not placed
        first = () if stages is None or settled else _first_attempts(valve, stages, i)
        loads = close_valve(valve, scene, material=mat, first=first,
                            x0=starts[i] if settled else None,
                            say=say if stages is None else _member_say(say, i))
        # the member's own solves (continuation, barrier closures) count as solve time;
        # its state check and stall probe, as the metrics, as host time
        own = sum(ls.report.wall_s + ls.start_s for ls in loads)
        wall_s += own
        t_driver += own
        c_driver += sum(ls.report.compile_s for ls in loads)
        compile_s += sum(ls.report.compile_s for ls in loads)
        xs = [ls.x for ls in loads]
        finite = [bool(np.all(np.isfinite(x))) for x in xs]
        say(f"measuring coaptation: member {i + 1}/{B}")
        m_he = measure(valve, xs[0], scene.g_c) if finite[0] else None
        m = measure(valve, xs[1], scene.g_c) if finite[1] else None
        out.append(BatchMember(index=i, model=model, material=mat, x=xs[1], x_he=xs[0],
                               metrics=m, metrics_he=m_he,
                               solves=tuple(ls.report for ls in loads)))
    solve_s = max(wall_s - compile_s, 0.0)
    say(f"  {sum(m.converged for m in out)}/{B} converged; {solve_s:.2f} s "
        f"(+{compile_s:.1f} s compile), {solve_s / B:.2f} s a member")
    t_m = time.perf_counter() - t0 - t_driver
    timings = dict(setup=setup, compile=compile_s, solve=solve_s, metrics=t_m,
                   follow_up=max(t_driver - c_driver, 0.0),
                   total=time.perf_counter() - t_all, per_scene=solve_s / B, retries=retries)
    res = BatchResult(scene=scene, valve=valve, model=model, members=tuple(out),
                      timings=timings, vectorized=bool(vectorize))
    if throw and not res.converged:
        bad = [res.members[i] for i in res.failed]
        raise ConvergenceError(
            f"{len(bad)} of {B} members did not converge (rtol {scene.rtol:g}): "
            + "; ".join(m.describe() for m in bad), res)
    return res
