"""Atomic clusters for ASE scenes: the hot EMT copper icosahedron of the adaptive-steps
benchmark and test (issue 58: 55 atoms at 2400 K, which melts)."""
from __future__ import annotations

import numpy as np


def hot_copper_cluster(shells: int = 3, temperature_K: float = 2400.0, seed: int = 3,
                       calc=None):
    """A copper Mackay icosahedron of ``shells`` shells (3: 55 atoms) with Maxwell-Boltzmann
    momenta at ``temperature_K`` drawn from ``seed``, its centre of mass at rest and no
    rotation; ``calc`` (default: ASE's EMT) attached."""
    from ase.calculators.emt import EMT
    from ase.cluster import Icosahedron
    from ase.md.velocitydistribution import Stationary, ZeroRotation, thermalize_momenta
    atoms = Icosahedron("Cu", noshells=shells)
    atoms.calc = EMT() if calc is None else calc
    thermalize_momenta(atoms, temperature_K=temperature_K, rng=np.random.default_rng(seed))
    Stationary(atoms)
    ZeroRotation(atoms)
    return atoms
