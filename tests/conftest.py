"""Test configuration: float64 everywhere, warnings are errors (see pyproject), XLA's
quicker-compiling CPU emitters, and one persistent XLA compilation cache for the run,
removed at its end."""
import os

#: The suite is compile-bound: most tests compile a program and run it for little time.
#: XLA's older CPU fusion emitters (what `jaxvalve.quick_jit` picks for short-running
#: programs) compile faster; the newer default ones make faster loops.  Measured on one
#: file at a time (session 19): tests/test_design.py 110.6 -> 91.7 s, tests/test_batch.py
#: 128.4 -> 115.0 s (CPU time 3m02 -> 2m29).  The suite passes with both; the benchmarks
#: and the CLI keep XLA's defaults.  JAXVALVE_TEST_DEFAULT_EMITTERS=1 runs the suite on
#: the defaults.  Set before JAX starts its CPU backend (xdist workers import this too),
#: the same way `import jaxvalve` adds its own flag (`jaxvalve.xla_setup.add_flag`).
from jaxvalve.xla_setup import add_flag, platform_summary

if os.environ.get("JAXVALVE_TEST_DEFAULT_EMITTERS") != "1":
    add_flag("--xla_cpu_use_fusion_emitters=false")

import jax  # noqa: E402

jax.config.update("jax_enable_x64", True)

import shutil
import tempfile

_CACHE_ENV = "JAXVALVE_TEST_XLA_CACHE"


#: Test files by their measured time in `.ci/run` (seconds of one xdist worker, session
#: 17, `--durations`), longest first.  With `--dist loadfile` the workers take whole files
#: from a queue; xdist's default queue puts the files with the most tests first, which left
#: the long files with few tests (the closure gradients, the notebooks) for the end, where
#: one worker ran them alone.  Longest first (LPT) keeps both workers busy to the end.
#: Files not listed follow in their usual order.
LONGEST_FIRST = (
    "tests/test_optimize.py",        # 189
    "tests/test_notebooks.py",       # 180
    "tests/test_adjoint.py",         # 175
    "tests/test_batch.py",           # 173
    "tests/test_contact.py",         # 162
    "tests/test_solvers.py",         # 141
    "tests/test_design.py",          # 136
    "tests/test_soft_pairs.py",      # 131
    "tests/stress/test_stress_special.py",   # 102
    "tests/test_coaptation.py",      # 95
    "tests/stress/test_stress_matrix.py",    # 78
    "tests/test_validation.py",      # 55
)


def pytest_collection_modifyitems(session, config, items):
    """Order the files longest first (`LONGEST_FIRST`); the order inside a file is kept."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    items.sort(key=lambda it: rank.get(it.nodeid.split("::")[0], len(rank)))


def pytest_configure(config):
    """The same programs (a valve closure at one mesh size, the metrics) are compiled by
    several test files, in two xdist workers.  The controlling process makes one
    temporary cache directory before the workers start (they inherit its path), and every
    process keeps its XLA executables there, so a program compiled once is loaded by the
    other files.  The in-memory jit caches that the no-recompilation tests count are not
    affected.  The user's own cache (``$JAXVALVE_CACHE_DIR``, used by the CLI) is never
    touched."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False      # keep the order above (xdist)
    if not hasattr(config, "workerinput") and _CACHE_ENV not in os.environ:
        os.environ[_CACHE_ENV] = tempfile.mkdtemp(prefix="jaxvalve-test-xla-")
        config._jaxvalve_cache = os.environ[_CACHE_ENV]
    os.environ["JAXVALVE_CACHE_DIR"] = os.environ[_CACHE_ENV]
    from jaxvalve.cli import enable_compilation_cache
    enable_compilation_cache()


def pytest_terminal_summary(terminalreporter):
    """One line naming the platform, so that a failure on another machine (the CI's) can be
    matched to its CPU and JAX release."""
    terminalreporter.write_line(f"jaxvalve test platform: {platform_summary()}")


def pytest_unconfigure(config):
    path = getattr(config, "_jaxvalve_cache", None)
    if path:
        shutil.rmtree(path, ignore_errors=True)
