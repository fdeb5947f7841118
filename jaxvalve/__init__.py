"""jaxvalve: differentiable membrane mechanics for aortic valve closure (Ozaki leaflets).

Importing jaxvalve switches JAX to float64 (the project's default precision).
"""
import warnings

import jax

jax.config.update("jax_enable_x64", True)

#: jax/jaxlib releases known to miscompile CPU programs silently (wrong numbers, no error).
#: 0.10.2: jax-ml/jax#39103, a vmapped small matrix-vector product followed by a reduction
#: gives wrong rows past 16384 under jit (reproduced in tests/test_platform.py).
#: pyproject.toml excludes them; an environment that has one anyway is warned at import.
MISCOMPILING_JAX = ("0.10.2",)

if jax.__version__ in MISCOMPILING_JAX:
    warnings.warn(f"jax {jax.__version__} is known to miscompile some CPU programs "
                  "(jax-ml/jax#39103); install another version, e.g. pip install "
                  "'jax==0.10.1' 'jaxlib==0.10.1'", RuntimeWarning, stacklevel=2)

from .equilibrium import solve  # noqa: E402
from .problem import Params, Problem, make_problem, mmhg  # noqa: E402
from .scene import Scene  # noqa: E402
from .simulation import SimulationResult, simulate  # noqa: E402
from .batch import BatchResult, simulate_batch  # noqa: E402

__version__ = "0.1.0"
__all__ = ["solve", "Params", "Problem", "make_problem", "mmhg", "Scene", "simulate",
           "SimulationResult", "simulate_batch", "BatchResult", "__version__"]
