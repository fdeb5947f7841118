"""Test configuration: float64 everywhere, warnings are errors (see pyproject), and one
persistent XLA compilation cache for the run, removed at its end."""
import jax

jax.config.update("jax_enable_x64", True)

import os
import shutil
import tempfile

_CACHE_ENV = "JAXVALVE_TEST_XLA_CACHE"


def pytest_configure(config):
    """The same programs (a valve closure at one mesh size, the metrics) are compiled by
    several test files, in two xdist workers.  The controlling process makes one
    temporary cache directory before the workers start (they inherit its path), and every
    process keeps its XLA executables there, so a program compiled once is loaded by the
    other files.  The in-memory jit caches that the no-recompilation tests count are not
    affected.  The user's own cache (``$JAXVALVE_CACHE_DIR``, used by the CLI) is never
    touched."""
    if not hasattr(config, "workerinput") and _CACHE_ENV not in os.environ:
        os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxvalve-test-xla-")
        config._jaxvalve_cache = os.environ[_CACHE_ENV]
    os.environ["JAXVALVE_CACHE_DIR"] = os.environ[_CACHE_ENV]
    from jaxvalve.cli import enable_compilation_cache
    enable_compilation_cache()


def pytest_unconfigure(config):
    path = getattr(config, "_jaxvalve_cache", None)
    if path:
        shutil.rmtree(path, ignore_errors=True)
