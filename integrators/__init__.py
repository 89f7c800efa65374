"""The mathematics of HBVM(k, s): tableau, spectra, the stepping engine, nonlinear solvers.

No ASE, no REBOUND here.
"""
from .engine import IntegrationResult, Stepper, integrate
from .equip import EQUIP
from .errors import AccumulatedErrorWarning, ConstraintError, ConvergenceError, EnergyConditionError, EnergyDriftError, NonFiniteError, StepError, StepSizeError, UnresolvedStepError
from .tableau import HBVM, gauss_collocation_tableau, gauss_matrix, gauss_spectrum
from .variational import VariationalStepper  # (importing it registers integrate(variational=))

__all__ = ["HBVM", "EQUIP", "Stepper", "integrate", "IntegrationResult", "ConvergenceError", "EnergyConditionError", "EnergyDriftError", "UnresolvedStepError",
           "NonFiniteError", "StepError", "AccumulatedErrorWarning", "ConstraintError", "StepSizeError",
           "gauss_spectrum", "gauss_matrix", "gauss_collocation_tableau", "VariationalStepper"]
