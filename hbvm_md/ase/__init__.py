"""The ASE host: :class:`HBVMDynamics`, an ASE ``MolecularDynamics`` class (NVE).

``dynamics`` holds the class and the atoms-as-a-system adapter.
"""
from .dynamics import HBVMDynamics, default_k

__all__ = ["HBVMDynamics", "default_k"]
