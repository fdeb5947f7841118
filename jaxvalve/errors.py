"""Exception types, and the one check of a positive scalar. Every message names the
offending parameter and its valid range."""
import math


class JaxvalveError(ValueError):
    """Base class for all jaxvalve input errors."""


class MeshError(JaxvalveError):
    """A mesh is broken: bad indices, degenerate or inconsistently oriented triangles, NaN."""


class ParameterError(JaxvalveError):
    """A physical or numerical parameter is outside its valid range."""


class RootFileError(JaxvalveError):
    """An input or output file is missing, unreadable or holds bad data (names the file)."""


class SurfaceFileError(RootFileError, MeshError):
    """A surface mesh file is missing, unreadable, has no triangles or holds bad data."""


class LandmarksFileError(RootFileError, ParameterError):
    """A landmarks file is missing, unreadable, or a field is missing or malformed."""


class ConvergenceError(RuntimeError):
    """An equilibrium solve did not converge; carries the solver's `Solution`."""

    def __init__(self, message, solution=None):
        super().__init__(message)
        self.solution = solution


class NeighbourListOverflow(RuntimeError):
    """A fixed-capacity contact pair list overflowed; rebuild with a larger capacity."""


def check_positive(name, value, unit="mm"):
    """float(value), or `ParameterError` naming ``name`` unless it is a finite number > 0
    (in ``unit``)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ParameterError(f"{name} must be a number > 0 {unit}; got {value!r}") from None
    if not math.isfinite(v) or v <= 0:
        raise ParameterError(f"{name} must be finite and > 0 {unit}; got {v}")
    return v
