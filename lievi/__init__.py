"""lievi: structure-preserving, differentiable variational integrators on Lie groups.

Implements Marsden, Pekarsky & Shkoller, *Discrete Euler–Poincaré and Lie–Poisson
equations*, Nonlinearity 12 (1999) 1647–1662, in JAX.
"""

from importlib.metadata import PackageNotFoundError, version

from . import diagnostics as diagnostics
from ._batch import has_fast_path as has_fast_path
from ._batch import shard_batch as shard_batch
from ._batch import simulate_batch as simulate_batch
from ._composition import Composition as Composition
from ._dep import DEP as DEP
from ._generalized_rigid_body import GeneralizedRigidBody as GeneralizedRigidBody
from ._group_base import MatrixLieGroup as MatrixLieGroup
from ._identification import InertiaFit as InertiaFit
from ._identification import fit_inertia as fit_inertia
from ._integrator_base import AbstractIntegrator as AbstractIntegrator
from ._integrator_base import AbstractVariationalIntegrator as AbstractVariationalIntegrator
from ._integrator_base import StepInfo as StepInfo
from ._lie_lagrangian import LieLagrangian as LieLagrangian
from ._moser_veselov import MoserVeselov as MoserVeselov
from ._preprocessed_dmv import PreprocessedMoserVeselov as PreprocessedMoserVeselov
from ._reference import reference_solution as reference_solution
from ._results import RESULTS as RESULTS
from ._rigid_body import RigidBody as RigidBody
from ._rk4 import RK4 as RK4
from ._simulate import Solution as Solution
from ._simulate import simulate as simulate
from ._so3 import SO3 as SO3
from ._so3 import SO3Group as SO3Group
from ._son import SOn as SOn
from ._splitting import LiePoissonSplitting as LiePoissonSplitting
from ._system_base import AbstractLieSystem as AbstractLieSystem

try:
    __version__ = version("lievi")
except PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"
