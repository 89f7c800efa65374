"""The ASE host: :class:`HBVMDynamics`, an ASE ``MolecularDynamics`` class (NVE).

``dynamics`` holds the class, ``atoms_system`` the atoms-as-a-system adapter that it and the
constrained step with rigid bonds (``holonomic``) both advance.
"""
from .dynamics import HBVMDynamics, default_k

__all__ = ["HBVMDynamics", "default_k"]
