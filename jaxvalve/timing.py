"""`compile_timer`: the part of a wall time that JAX spent tracing and compiling."""
from __future__ import annotations

import jax

__all__ = ["compile_timer"]


class compile_timer:
    """Context manager that sums JAX's tracing, lowering and XLA compile durations (s)
    reported through `jax.monitoring` while it is open (``.seconds``)."""

    _EVENTS = ("/jax/core/compile/jaxpr_trace_duration",
               "/jax/core/compile/jaxpr_to_mlir_module_duration",
               "/jax/core/compile/backend_compile_duration")
    _active: list = []
    _registered = False

    def __init__(self):
        self.seconds = 0.0

    @classmethod
    def _listener(cls, event, duration, **kw):
        if event in cls._EVENTS:
            for t in cls._active:
                t.seconds += duration

    def __enter__(self):
        if not compile_timer._registered:
            jax.monitoring.register_event_duration_secs_listener(compile_timer._listener)
            compile_timer._registered = True
        compile_timer._active.append(self)
        return self

    def __exit__(self, *exc):
        compile_timer._active.remove(self)
        return False
