"""Equilibrium solvers: the paper's fixed point, FIRE and Newton-Krylov."""
from .barrier_newton import BarrierNewton, solve_barrier
from .base import RESULTS, EquilibriumSystem, Solution, Stats, iterate
from .fire import FIRE
from .fixed_point import FixedPoint
from .newton import NewtonKrylov
from .predictor import BulgePredictor

__all__ = ["RESULTS", "EquilibriumSystem", "Solution", "Stats", "iterate", "FIRE",
           "FixedPoint", "NewtonKrylov", "BulgePredictor", "BarrierNewton", "solve_barrier"]
