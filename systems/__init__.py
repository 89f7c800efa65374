"""Hamiltonian models: the classic test problems, N-body gravity and pair potentials.

See :mod:`systems.base` for the protocol a system follows.  Models that need ASE or astropy
are imported lazily.
"""
from importlib import import_module

from .base import HamiltonianSystem, SeparableSystem
from .fpu import FPU
from .henon_heiles import HenonHeiles
from .kepler import Kepler
from .pendulum import Morse, Pendulum
from .poincare import PoincareKepler, PoincareTransformed, distance_power

_LAZY = {
    "PolynomialPairPotential": "systems.pair_potential",
    "NBody": "systems.nbody",
    "outer_solar_system": "systems.solar",
    "solar_system": "systems.solar",
    "hot_copper_cluster": "systems.clusters",
}

__all__ = ["HamiltonianSystem", "SeparableSystem",
           "Kepler", "HenonHeiles", "FPU", "Pendulum", "Morse", "PoincareTransformed",
           "PoincareKepler", "distance_power", *_LAZY]


def __getattr__(name):
    if name in _LAZY:
        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module 'systems' has no attribute {name!r}")
