"""Input and output: patient roots and surfaces through meshio (`files`, the only module
that imports meshio), the outputs of a simulation (`report`: metrics.json and .vtu;
`plots`: PNG figures; `html_report`: the self-contained report.html) and plain JSON data
(`jsonable`).

``from jaxvalve import io`` gives `files`' API (``io.read_root``, ...)."""
import importlib

#: `files`'s API, read on first use (PEP 562): importing this package imports nothing
#: else, so its modules may be imported from anywhere without an import cycle
_API = (
        'UNITS', 'LandmarksFileError', 'RootFileError', 'SurfaceFileError',
        'check_out_dir', 'read_landmarks', 'read_root', 'read_surface',
        'write_landmarks', 'write_root', 'write_surface')


def __getattr__(name):
    if name in _API:
        return getattr(importlib.import_module(f"{__name__}.files"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
