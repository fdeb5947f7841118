"""Test configuration: float64 everywhere, warnings are errors (see pyproject), XLA's
quicker-compiling CPU emitters, and no persistent XLA compilation cache: every worker runs
the executables it compiled itself."""
import os

import pytest


def _pin_worker():
    """Pin each xdist worker to one CPU of its own (gw0 to the first allowed CPU, gw1 to
    the next, ...), before JAX, NumPy or SciPy start their thread pools, which size
    themselves by the CPUs a process may use.  With two workers on two cores each process
    then runs XLA's intra-op work, LLVM's compilation and OpenBLAS on one core, in one
    thread each, instead of four such pools contending for two cores: the CI's
    intermittent wrong results (docs/known-limits.md) were only ever seen with several
    threads per process.  A single-process run (no xdist) is left as it is."""
    worker = os.environ.get("PYTEST_XDIST_WORKER", "")
    if not worker.startswith("gw") or not hasattr(os, "sched_setaffinity"):
        return
    cpus = sorted(os.sched_getaffinity(0))
    n = int(os.environ.get("PYTEST_XDIST_WORKER_COUNT", "0") or 0)
    if len(cpus) > 1 and 0 < n <= len(cpus):
        os.sched_setaffinity(0, {cpus[int(worker[2:]) % len(cpus)]})


_pin_worker()

#: The suite is compile-bound: most tests compile a program and run it for little time.
#: XLA's older CPU fusion emitters compile faster; the newer default ones make faster
#: loops.  Measured on one
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


def _load_stress_suite():
    """`benchmarks/stress_suite.py`, the stress suite's harness (a benchmark, not part of
    the library), as the module ``stress_suite``: `tests/stress/` runs a small part of the
    suite, and a few closure tests use its hard starts and its ipctk check.  Loaded by
    path: the benchmarks folder is not put on sys.path, where its scripts (optimize.py,
    batch.py, ...) would shadow the packages of the same names."""
    import importlib.util
    import pathlib
    import sys

    path = pathlib.Path(__file__).resolve().parents[1] / "benchmarks" / "stress_suite.py"
    spec = importlib.util.spec_from_file_location("stress_suite", path)
    module = importlib.util.module_from_spec(spec)
    sys.modules["stress_suite"] = module
    spec.loader.exec_module(module)


_load_stress_suite()

#: Test files by their measured time (seconds of one xdist worker, `pytest -n 2 --dist
#: loadfile --durations=0`, summed over each file's setup and calls), longest first.  The
#: workers take whole files (`SAME_WORKER`: whole groups of files) from a queue; xdist's
#: default queue puts the files with the most tests first, which left the long files
#: with few tests for the end, where one worker ran them alone.  Longest first (LPT)
#: keeps both workers busy to the end.  Files not listed follow in their usual order.
LONGEST_FIRST = (
    "tests/stress/test_stress_special.py",   # 520
    "tests/test_optimize.py",        # 195, with test_notebooks (SAME_WORKER)
    "tests/test_patient_root.py",    # 200
    "tests/test_adjoint.py",         # 133
    "tests/test_engine.py",
    "tests/test_design.py",          # 126
    "tests/test_admissible_start.py",  # 124
    "tests/test_batch.py",           # 121
    "tests/test_pairs.py",
    "tests/test_contact.py",         # 120
    "tests/test_solvers.py",         # 118
    "tests/test_docs.py",            # 101
    "tests/stress/test_stress_matrix.py",    # 81
    "tests/test_notebooks.py",       # 175 alone; after test_optimize: SAME_WORKER
    "tests/test_energies.py",        # 56
)

#: Files that run in the worker of another file, right after it, as one unit of the
#: queue (`pytest_xdist_make_scheduler`), because they compile the same programs: the
#: second then runs on the first's (notebook 02 and test_optimize: the evaluator's
#: valve, h = 2.5 mm at 3 mmHg; test_valve_closure and test_engine: the benchmark valve
#: at h = 1.5 mm).
SAME_WORKER = {"tests/test_notebooks.py": "tests/test_optimize.py",
               "tests/test_valve_closure.py": "tests/test_engine.py"}


@pytest.hookimpl(tryfirst=True, optionalhook=True)
def pytest_xdist_make_scheduler(config, log):
    """``--dist loadfile`` with `SAME_WORKER`: whole files go to the workers, a
    `SAME_WORKER` file with its partner's.  (xdist's own ``loadgroup`` would do this by
    marks, but with pytest 9.2 and xdist 3.8 it silently sends each test on its own: it
    renames the items through an attribute that pytest 9.2 no longer reads.)"""
    if config.getvalue("dist") != "loadfile":
        return None
    from xdist.scheduler import LoadFileScheduling

    class _SameWorker(LoadFileScheduling):
        def _split_scope(self, nodeid):
            f = nodeid.split("::", 1)[0]
            return SAME_WORKER.get(f, f)

    return _SameWorker(config, log)


def _file(item):
    return item.nodeid.split("::")[0]


def pytest_collection_modifyitems(session, config, items):
    """Order the files longest first (`LONGEST_FIRST`, a `SAME_WORKER` file right after
    its partner); the order inside a file is kept.  Every test of a `LONGEST_FIRST` file
    is marked ``slow``: ``pytest -m "not slow"`` is the fast tier for development
    (docs/development.md); the CI runs all."""
    rank = {name: i for i, name in enumerate(LONGEST_FIRST)}
    last = len(rank)

    def key(it):
        f = _file(it)
        lead = SAME_WORKER.get(f)
        return (rank.get(lead, last), 1, rank.get(f, last)) if lead else (rank.get(f, last), 0, 0)

    items.sort(key=key)
    for it in items:
        if _file(it) in rank:
            it.add_marker(pytest.mark.slow)


def pytest_configure(config):
    """Keep the order above (xdist), and run without a persistent compilation cache.

    A cache shared by the two workers saved about a minute of compilation, but every
    executable it reloads comes with XLA's "machine type used for compilation doesn't
    match" error on this CPU family (jax-ml/jax#38445), and JAX writes its entries without
    a lock or an atomic rename.  The CI's intermittent wrong results (docs/known-limits.md)
    never reproduced here, with the cache or without; a correctness suite should not run
    programs that XLA itself flags, so the suite compiles what it runs.  The user's own
    cache (``$JAXVALVE_CACHE_DIR``, used by the CLI) is never touched: it is set to off
    for the test processes."""
    if hasattr(config.option, "loadscopereorder"):
        config.option.loadscopereorder = False      # keep the order above (xdist)
    os.environ["JAXVALVE_CACHE_DIR"] = "off"


def pytest_sessionstart(session):
    """The platform line first as well: the CI shows the head of a failing run's output."""
    reporter = session.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None and not os.environ.get("PYTEST_XDIST_WORKER"):
        reporter.write_line(f"jaxvalve test platform: {platform_summary()}")


def pytest_terminal_summary(terminalreporter):
    """One line naming the platform, so that a failure on another machine (the CI's) can be
    matched to its CPU and JAX release."""
    terminalreporter.write_line(f"jaxvalve test platform: {platform_summary()}")
