"""How jaxvalve sets up XLA's CPU compiler when it is imported.

jaxlib 0.10 hands some dot products, with the reductions around them, to YNNPACK
(``__ynn_fusion``).  Those fusions have given wrong numbers without an error
(jax-ml/jax#39103: rows past 16384 of a vmapped 3x3 matrix-vector product and sum, on
0.10.2) and crashes or hangs that depend on the CPU (jax-ml/jax#39257).  (In jaxvalve,
compiled on an AVX2 machine, they sat in the Newton preconditioner's element Hessians.)
jaxvalve's programs hold only small dots (3x3 element maps, 2x2 and 3x3 blocks), where
YNNPACK buys nothing: the benchmark valve's closure and the default optimisation take the
same time with and without it.  So jaxvalve turns the YNNPACK fusions off (XLA's own emitters
compile those dots) by adding `NO_YNN_FLAG` to ``XLA_FLAGS`` before JAX starts its CPU
backend.  Set ``JAXVALVE_ALLOW_YNN=1``, or name the flag in ``XLA_FLAGS`` yourself, to
keep XLA's choice.  If the backend has already started when jaxvalve is imported, the
flag can no longer take effect, and a warning says so.
"""
from __future__ import annotations

import os
import warnings

#: the XLA flag (an empty list of fusion kinds) that turns the YNNPACK fusions off
NO_YNN_FLAG = "--xla_cpu_experimental_ynn_fusion_type="

#: jax/jaxlib releases known to miscompile CPU programs silently (wrong numbers, no
#: error); pyproject.toml excludes them and `configure` warns where one is installed.
#: 0.10.2: jax-ml/jax#39103 (reproduced in tests/test_platform.py; correct on 0.10.1).
MISCOMPILING_JAX = ("0.10.2",)


def add_flag(flag: str) -> None:
    """Append ``flag`` to ``XLA_FLAGS`` unless it is there already.  XLA reads the flags
    when JAX starts its backend, so this acts only before the first computation."""
    flags = os.environ.get("XLA_FLAGS", "")
    if flag not in flags.split():
        os.environ["XLA_FLAGS"] = (flags + " " + flag).strip()


def ynn_disabled() -> bool:
    """True when ``XLA_FLAGS`` turns the YNNPACK fusions off (as `configure` sets it)."""
    return NO_YNN_FLAG in os.environ.get("XLA_FLAGS", "").split()


def platform_summary() -> str:
    """One line naming the jax and jaxlib releases, the CPU (model, cores, ISA, from
    /proc/cpuinfo where there is one) and ``XLA_FLAGS``, so that a timing or a test
    failure can be matched to its machine (test logs, `benchmarks/optimize_cli.py`)."""
    import platform

    import jax
    import jaxlib

    model, flags, ident = platform.processor() or platform.machine(), set(), {}
    try:
        with open("/proc/cpuinfo") as f:
            for line in f:
                key, _, value = line.partition(":")
                key = key.strip()
                if key == "model name":
                    model = value.strip()
                elif key in ("cpu family", "model") and key not in ident:
                    ident[key] = value.strip()
                elif key == "flags":
                    flags = set(value.split())
                    break
    except OSError:
        pass
    if ident:      # VMs often name the CPU vaguely ("AMD EPYC"): family and model tell more
        model += f" (family {ident.get('cpu family', '?')} model {ident.get('model', '?')})"
    isa = "/".join(n for n in ("avx512f", "avx2", "avx", "fma") if n in flags) or "unknown"
    return (f"jax {jax.__version__}, jaxlib {jaxlib.__version__}, {model}, "
            f"{os.cpu_count()} cores, ISA {isa}, "
            f"XLA_FLAGS={os.environ.get('XLA_FLAGS', '')!r}")


def configure() -> None:
    """Add `NO_YNN_FLAG` to ``XLA_FLAGS`` (unless opted out) and warn about a known
    miscompiling jax release.  Called once, by ``import jaxvalve``."""
    import jax
    from jax._src import xla_bridge

    if jax.__version__ in MISCOMPILING_JAX:
        warnings.warn(f"jax {jax.__version__} is known to miscompile some CPU programs "
                      "(jax-ml/jax#39103); install another release, e.g. pip install "
                      "'jax==0.10.1' 'jaxlib==0.10.1'", RuntimeWarning, stacklevel=3)
    user_set = "xla_cpu_experimental_ynn_fusion_type" in os.environ.get("XLA_FLAGS", "")
    if os.environ.get("JAXVALVE_ALLOW_YNN") == "1" or user_set:
        return
    if xla_bridge.backends_are_initialized():
        warnings.warn("JAX's backend started before jaxvalve was imported, so XLA's YNNPACK "
                      "fusions stay on (jax-ml/jax#39103, #39257); import jaxvalve first, or "
                      f"set XLA_FLAGS={NO_YNN_FLAG}", RuntimeWarning, stacklevel=3)
        return
    add_flag(NO_YNN_FLAG)
