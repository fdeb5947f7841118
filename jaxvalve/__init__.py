"""jaxvalve: differentiable membrane mechanics for aortic valve closure (Ozaki leaflets).

Importing jaxvalve switches JAX to float64 (the project's default precision) and turns
XLA's YNNPACK CPU fusions off (`jaxvalve.xla_setup`; ``JAXVALVE_ALLOW_YNN=1`` keeps them).
"""
import jax

jax.config.update("jax_enable_x64", True)

from . import xla_setup  # noqa: E402

xla_setup.configure()     # XLA's YNNPACK fusions off (see xla_setup), before any compile

from .solvers.equilibrium import solve  # noqa: E402
from .mechanics.problem import Params, Problem, make_problem, mmhg  # noqa: E402
from .scene import Scene  # noqa: E402
from .simulation import SimulationResult, simulate  # noqa: E402
from .batch import BatchResult, simulate_batch  # noqa: E402

__version__ = "0.1.0"
__all__ = ["solve", "Params", "Problem", "make_problem", "mmhg", "Scene", "simulate",
           "SimulationResult", "simulate_batch", "BatchResult", "__version__"]
