"""A simulation scene: root, template, mesh size, material, load, contact law and solver.

`Scene()` is the benchmark valve (the paper's Table 1 setting; docs/benchmark-notes.md).  A
scene is plain data; it can be read from TOML (`Scene.from_toml`) and every field can be
overridden.

Benchmark template (chosen from anatomy before any closure was run; docs/benchmark-notes.md):
free edge 2b = 30 mm (Labrosse et al. 2006, free-edge length 30 mm), arc radius r = 12 mm
(the annulus radius, so the belly's arc matches the annulus), alpha = 160 degrees (the
paper), and a = 7.1 mm, which makes the sutured edge 47.71 mm: the length of the benchmark
suturing path whose commissures stand at the valve height of 16.8 mm (Labrosse).  The root
is fitted to this length (`jaxvalve.geometry.root.benchmark_root`), giving H_c = 16.8 mm.
h = 0.88 mm gives 1329 triangles a leaflet, the paper's ~1313.
"""
from __future__ import annotations

import dataclasses
import math
import tomllib
from pathlib import Path

from .errors import ParameterError
from .geometry.template import Template

__all__ = ["Scene", "BENCHMARK_TEMPLATE", "BENCHMARK_H", "MODELS", "SOLVERS", "PRECISIONS"]

BENCHMARK_TEMPLATE = Template(r=12.0, a=7.1, b=15.0, alpha=160.0)
BENCHMARK_H = 0.88
MODELS = ("mass-spring", "stvk", "neo-hookean", "gent")
#: "engine": the IPC barrier contact, closed by FIRE and a Newton finish
#: (`jaxvalve.solvers.Engine`); "paper": the paper's contact law (2.2) and its damped
#: fixed point, Algorithm 2.1, for comparison with the paper
SOLVERS = ("engine", "paper")
PRECISIONS = ("float64", "float32")


@dataclasses.dataclass(frozen=True)
class Scene:
    """Everything a closure needs (units mm, MPa, mmHg, degrees).

    root: "benchmark", or ``(surface_file, landmarks_file)`` of a patient root.
    model: one of MODELS.  E (MPa), nu (StVK and the mass-spring Poisson-free law ignore
    nu where unused), mu (MPa; default E/3 for neo-Hookean and Gent), Jm (Gent),
    E1/E2/E3 (MPa; the mass-spring piecewise modulus 3.3; default: linear, E everywhere),
    fibre_angle (degrees, template frame; anisotropic mass-spring only).
    pressure, he_pressure: the closing load and the effective-height load (mmHg).
    rtol: relative force residual ||F_free|| / ||F_pressure|| the closure must reach
    (default 1e-4: the coaptation metrics then agree with a 1e-6 solve to ~0.01 mm; see
    docs/benchmark-notes.md, "Run time against error").
    bending: plate bending stiffness as a multiple of the physical D = E H^3 / (12 (1 -
    nu^2)) (`jaxvalve.mechanics.bending`); 0 gives the specified pure membrane.
    solver: "engine" (default: the IPC barrier contact, FIRE and a Newton finish) or
    "paper" (the paper's contact law and Algorithm 2.1, for comparison).  max_steps:
    the engine's FIRE steps a solve (or Algorithm 2.1's).
    precision: the floating type of the solve, "float64" (default) or "float32" (states,
    parameters and forces; the metrics are always measured in float64).
    """

    r: float = BENCHMARK_TEMPLATE.r
    a: float = BENCHMARK_TEMPLATE.a
    b: float = BENCHMARK_TEMPLATE.b
    alpha: float = BENCHMARK_TEMPLATE.alpha
    h: float = BENCHMARK_H
    root: object = "benchmark"
    model: str = "stvk"
    E: float = 1.0
    nu: float = 0.45
    mu: float | None = None
    Jm: float = 2.3
    E1: float | None = None
    E2: float | None = None
    E3: float | None = None
    fibre_angle: float = 0.0
    thickness: float = 0.3
    pressure: float = 80.0
    he_pressure: float = 3.0
    solver: str = "engine"
    rtol: float = 1e-4
    max_steps: int = 20_000
    g_c: float = 0.5
    bending: float = 1.0
    precision: str = "float64"

    def __post_init__(self):
        if self.model not in MODELS:
            raise ParameterError(f"model must be one of {MODELS}; got {self.model!r}")
        if self.solver not in SOLVERS:
            raise ParameterError(f"solver must be one of {SOLVERS}; got {self.solver!r}")
        if self.precision not in PRECISIONS:
            raise ParameterError(f"precision must be one of {PRECISIONS}; "
                                 f"got {self.precision!r}")
        for name in ("h", "thickness", "g_c", "rtol"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be a finite number > 0; got {v!r}")
        for name in ("pressure", "he_pressure"):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and math.isfinite(v) and v > 0):
                raise ParameterError(f"{name} must be a finite pressure > 0 mmHg; got {v!r}")
        if self.he_pressure > self.pressure:
            raise ParameterError(f"he_pressure must be at most pressure = {self.pressure:g} "
                                 f"mmHg (the effective-height load comes first, on the way "
                                 f"to the closing load); got {self.he_pressure:g} mmHg")
        if not (isinstance(self.bending, (int, float)) and math.isfinite(self.bending)
                and self.bending >= 0):
            raise ParameterError(f"bending must be a finite multiple >= 0 of the plate modulus; "
                                 f"got {self.bending!r}")
        if not (isinstance(self.max_steps, int) and self.max_steps > 0):
            raise ParameterError(f"max_steps must be a positive integer; got {self.max_steps!r}")
        self.template()  # validates r, a, b, alpha

    @property
    def dtype(self):
        """The NumPy floating type of the solve (`precision`)."""
        import numpy as np
        return np.dtype(self.precision)

    def replace(self, **kw) -> "Scene":
        return dataclasses.replace(self, **kw)

    def template(self) -> Template:
        return Template(r=self.r, a=self.a, b=self.b, alpha=self.alpha)

    def material(self):
        """The material law with its parameters (validated)."""
        from .mechanics import materials as m
        if self.model == "stvk":
            mat = m.StVenantKirchhoff(E=self.E, nu=self.nu)
        elif self.model == "neo-hookean":
            mat = m.NeoHookean(mu=self.E / 3 if self.mu is None else self.mu)
        elif self.model == "gent":
            mat = m.Gent(mu=self.E / 3 if self.mu is None else self.mu, Jm=self.Jm)
        else:
            given = [v is not None for v in (self.E1, self.E2, self.E3)]
            if any(given) and not all(given):
                raise ParameterError("mass-spring: give all of E1, E2, E3 (MPa) or none")
            if all(given):
                mat = m.MassSpring(E1=self.E1, E2=self.E2, E3=self.E3)
            else:
                mat = m.MassSpring.linear(self.E)
        return mat.validate()

    def load_root(self):
        """The `AorticRoot`: the benchmark fitted to this template, or read from files."""
        if isinstance(self.root, str) and self.root == "benchmark":
            from .geometry.root import benchmark_root
            return benchmark_root(self.template().sutured_length)
        try:
            surface, landmarks = self.root
        except (TypeError, ValueError):
            raise ParameterError("root must be 'benchmark' or (surface_file, landmarks_file); "
                                 f"got {self.root!r}") from None
        from .io.files import read_root
        return read_root(surface, landmarks, sutured_length=self.template().sutured_length)

    def contact_law(self):
        """The contact law: the IPC barrier (the engine's), or the paper's (2.2)."""
        from .contact import BarrierContact, PaperContact
        return BarrierContact() if self.solver == "engine" else PaperContact()

    def bending_law(self):
        """`Bending` (or None for a pure membrane, bending = 0)."""
        from .mechanics.bending import Bending
        return Bending(float(self.bending)) if self.bending > 0 else None

    def make_solver(self):
        """The engine (`jaxvalve.solvers.Engine`), or Algorithm 2.1 (`FixedPoint`)."""
        from .solvers import Engine, FixedPoint
        if self.solver == "engine":
            return Engine(rtol=self.rtol, max_steps=self.max_steps)
        return FixedPoint(max_steps=self.max_steps)

    def as_dict(self) -> dict:
        d = dataclasses.asdict(self)
        if not isinstance(self.root, str):
            d["root"] = [str(p) for p in self.root]
        return d

    @classmethod
    def from_toml(cls, path, **overrides) -> "Scene":
        """Read a scene from a TOML file (keys = field names); ``overrides`` win."""
        p = Path(path)
        if not p.is_file():
            raise ParameterError(f"scene file {str(p)!r} does not exist")
        try:
            data = tomllib.loads(p.read_text())
        except (tomllib.TOMLDecodeError, UnicodeDecodeError) as e:
            raise ParameterError(f"scene file {str(p)!r} is not valid TOML: {e}") from None
        names = {f.name for f in dataclasses.fields(cls)}
        unknown = sorted(set(data) - names)
        if unknown:
            raise ParameterError(f"scene file {str(p)!r}: unknown keys {unknown}; valid keys "
                                 f"are {sorted(names)}")
        if isinstance(data.get("root"), list):
            data["root"] = tuple(str((p.parent / q).resolve()) for q in data["root"])
        data.update({k: v for k, v in overrides.items() if v is not None})
        return cls(**data)
