"""Small ASE scenes the conservation audit is shown and tested on (:mod:`hbvm_md.reports.audit`,
``docs/guide/audit.md``): a head-on EMT Cu2 pair that crosses EMT's cutoff, a warm 13-atom
Lennard-Jones cluster, and a Lennard-Jones calculator whose forces are not the gradient of its
energy.  One definition for the tests, the benchmark and the guide."""
from __future__ import annotations

import numpy as np
from ase import Atoms, units
from ase.calculators.emt import EMT
from ase.calculators.lj import LennardJones
from ase.cluster import Icosahedron

#: the Cu-Cu distance where EMT's energy steps (its cutoff, as ASE's EMT computes it), in A
EMT_CU_CUTOFF = 5.8768


class ScaledForcesLJ(LennardJones):
    """Lennard-Jones whose forces are ``scale`` times the energy's gradient: not conservative
    (a toy for the audit's non-conservative work)."""

    def __init__(self, scale: float = 1.03, **kwargs):
        super().__init__(**kwargs)
        self.scale = float(scale)

    def calculate(self, *args, **kwargs):
        super().calculate(*args, **kwargs)
        self.results["forces"] = self.results["forces"] * self.scale


def cu2_pair(distance: float = 6.0, speed: float = 0.03) -> Atoms:
    """A head-on Cu2 pair with EMT, ``distance`` A apart, each atom at ``speed`` A/fs towards
    the other."""
    atoms = Atoms("Cu2", positions=[[0.0, 0.0, 0.0], [distance, 0.0, 0.0]])
    atoms.calc = EMT()
    m = atoms.get_masses()[0]
    v = speed / units.fs
    atoms.set_momenta([[m * v, 0, 0], [-m * v, 0, 0]])
    return atoms


def lj_cluster(calc, seed: int = 1) -> Atoms:
    """13 atoms (sigma = 1 A, epsilon = 1 eV, argon's mass) near the icosahedron, warm."""
    atoms = Icosahedron("Ar", noshells=2, latticeconstant=2 ** (1 / 6) * np.sqrt(2))
    rng = np.random.default_rng(seed)
    atoms.positions += 0.03 * rng.standard_normal(atoms.positions.shape)
    atoms.set_momenta(rng.standard_normal((len(atoms), 3)) * np.sqrt(40 * 0.02))
    atoms.calc = calc
    return atoms
