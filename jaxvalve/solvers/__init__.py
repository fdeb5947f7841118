"""Equilibrium solvers: the engine (FIRE, then a Newton finish), the paper's fixed point
and Newton-Krylov for membranes without contact."""
from .base import RESULTS, EquilibriumSystem, Solution, Stats, iterate
from .equilibrium import Engine, solve
from .fire import FIRE
from .fixed_point import FixedPoint
from .newton import NewtonKrylov
from .predictor import BulgePredictor

__all__ = ["RESULTS", "EquilibriumSystem", "Solution", "Stats", "iterate", "Engine", "solve",
           "FIRE", "FixedPoint", "NewtonKrylov", "BulgePredictor"]
