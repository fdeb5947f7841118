"""Re-exports read on first use (PEP 562), for the packages whose name was a module's:
``jaxvalve.valve`` offers `valve.model`'s API and ``jaxvalve.io`` `io.files`', yet
importing either package imports nothing else, so their modules can be imported from
anywhere without an import cycle."""
from __future__ import annotations

import importlib
import sys

__all__ = ["lazy_exports"]


def lazy_exports(package: str, module: str, names) -> tuple:
    """(__getattr__, __dir__) for ``package``: the attributes ``names`` are those of
    ``package.module``, imported when one is first read."""
    api = tuple(names)

    def __getattr__(name):
        if name in api:
            return getattr(importlib.import_module(f"{package}.{module}"), name)
        raise AttributeError(f"module {package!r} has no attribute {name!r}")

    def __dir__():
        return sorted(set(vars(sys.modules[package])) | set(api))

    return __getattr__, __dir__
