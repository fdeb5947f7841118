"""The valve: three leaflets placed in the root (`placement`), stacked into one problem
and closed under pressure (`model`: `build_valve`, `settle`, `close`), the one closure
driver of every caller (`closure`), the state checks of a closed valve (`checks`,
`intersect`: folds, collapsed triangles, crossing leaflets) and the template-to-valve map
that gradients in r, a and b go through (`design`).

``from jaxvalve import valve`` gives `model`'s API (``valve.build_valve``, ...)."""
import importlib

#: `model`'s API, read on first use (PEP 562): importing this package imports nothing
#: else, so its modules may be imported from anywhere without an import cycle
_API = (
        'STATE_FAILURES', 'Valve', 'ValveSolution', 'build_valve', 'checked', 'close',
        'commissure_groups', 'leaflet_crossings', 'settle', 'state_failure',
        'valve_contact')


def __getattr__(name):
    if name in _API:
        return getattr(importlib.import_module(f"{__name__}.model"), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


def __dir__():
    return sorted(set(globals()) | set(_API))
