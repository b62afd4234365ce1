"""lievi: structure-preserving, differentiable variational integrators on Lie groups.

Implements Marsden, Pekarsky & Shkoller, *Discrete Euler–Poincaré and Lie–Poisson
equations*, Nonlinearity 12 (1999) 1647–1662, in JAX.
"""

from importlib import metadata as _metadata

from . import advanced as advanced
from . import diagnostics as diagnostics
from ._forcing import AbstractForcing as AbstractForcing
from ._forcing import Control as Control
from ._forcing import ForceLaw as ForceLaw
from ._groups._base import MatrixLieGroup as MatrixLieGroup
from ._groups._conversions import euler_to_matrix as euler_to_matrix
from ._groups._conversions import from_scipy_rotation as from_scipy_rotation
from ._groups._conversions import matrix_to_euler as matrix_to_euler
from ._groups._conversions import matrix_to_quaternion_wxyz as matrix_to_quaternion_wxyz
from ._groups._conversions import matrix_to_quaternion_xyzw as matrix_to_quaternion_xyzw
from ._groups._conversions import matrix_to_rotation_vector as matrix_to_rotation_vector
from ._groups._conversions import quaternion_wxyz_to_matrix as quaternion_wxyz_to_matrix
from ._groups._conversions import quaternion_xyzw_to_matrix as quaternion_xyzw_to_matrix
from ._groups._conversions import rotation_vector_to_matrix as rotation_vector_to_matrix
from ._groups._conversions import to_scipy_rotation as to_scipy_rotation
from ._groups._conversions import wxyz_to_xyzw as wxyz_to_xyzw
from ._groups._conversions import xyzw_to_wxyz as xyzw_to_wxyz
from ._groups._interop import from_jaxlie as from_jaxlie
from ._groups._interop import to_jaxlie as to_jaxlie
from ._groups._interop import twist_from_jaxlie as twist_from_jaxlie
from ._groups._interop import twist_to_jaxlie as twist_to_jaxlie
from ._groups._se3 import SE3 as SE3
from ._groups._se3 import SE3Group as SE3Group
from ._groups._so3 import SO3 as SO3
from ._groups._so3 import SO3Group as SO3Group
from ._groups._son import SOn as SOn
from ._identification._fit import fit_inertia as fit_inertia
from ._identification._fit import fit_system as fit_system
from ._identification._result import FIT_REASONS as FIT_REASONS
from ._identification._result import SystemFit as SystemFit
from ._integrators._base import AbstractIntegrator as AbstractIntegrator
from ._integrators._base import AbstractKickIntegrator as AbstractKickIntegrator
from ._integrators._base import AbstractVariationalIntegrator as AbstractVariationalIntegrator
from ._integrators._base import StepInfo as StepInfo
from ._integrators._composition import Composition as Composition
from ._integrators._dep import DEP as DEP
from ._integrators._moser_veselov import MoserVeselov as MoserVeselov
from ._integrators._preprocessed_dmv import PreprocessedMoserVeselov as PreprocessedMoserVeselov
from ._integrators._rattle import RATTLE as RATTLE
from ._integrators._rk4 import RK4 as RK4
from ._integrators._rkmk import RKMK4 as RKMK4
from ._integrators._rkmk import RKMK5 as RKMK5
from ._integrators._rkmk import RKMK8 as RKMK8
from ._integrators._rkmk import AbstractRKMK as AbstractRKMK
from ._integrators._splitting import LiePoissonSplitting as LiePoissonSplitting
from ._integrators._symmetric_top import SymmetricTopSplitting as SymmetricTopSplitting
from ._monitor import AbstractInvariantMonitor as AbstractInvariantMonitor
from ._monitor import EnergyMonitor as EnergyMonitor
from ._monitor import MomentumMonitor as MomentumMonitor
from ._optimal_control import OptimalControlSolution as OptimalControlSolution
from ._optimal_control import solve_optimal_control as solve_optimal_control
from ._progress import NoProgressMeter as NoProgressMeter
from ._progress import TextProgressMeter as TextProgressMeter
from ._progress import TqdmProgressMeter as TqdmProgressMeter
from ._reference import reference_solution as reference_solution
from ._results import RESULTS as RESULTS
from ._save import Save as Save
from ._sharding import gather_batch as gather_batch
from ._sharding import process_rows as process_rows
from ._sharding import shard_batch as shard_batch
from ._sharding import shard_process_batch as shard_process_batch
from ._simulate import simulate as simulate
from ._simulate_batch import simulate_batch as simulate_batch
from ._simulate_neighbors import simulate_with_neighbor_list as simulate_with_neighbor_list
from ._solution import Solution as Solution
from ._stream import stream_batch as stream_batch
from ._stream_writer import AbstractStreamWriter as AbstractStreamWriter
from ._stream_writer import ChunkState as ChunkState
from ._stream_writer import NpyWriter as NpyWriter
from ._stream_writer import StreamLayout as StreamLayout
from ._suggest import Suggestion as Suggestion
from ._suggest import suggest_integrator as suggest_integrator
from ._systems._articulated import ArticulatedBodies as ArticulatedBodies
from ._systems._base import AbstractLieSystem as AbstractLieSystem
from ._systems._couplings import SitePotential as SitePotential
from ._systems._couplings import SiteSprings as SiteSprings
from ._systems._dipoles import DipoleCoupling as DipoleCoupling
from ._systems._generalized_rigid_body import GeneralizedRigidBody as GeneralizedRigidBody
from ._systems._joints import BallJoint as BallJoint
from ._systems._joints import HingeJoint as HingeJoint
from ._systems._lie_lagrangian import LieLagrangian as LieLagrangian
from ._systems._mutual_gravity import MutualGravity as MutualGravity
from ._systems._mutual_gravity import gravitating_bodies as gravitating_bodies
from ._systems._neighbors import AbstractNeighborBuilder as AbstractNeighborBuilder
from ._systems._neighbors import BruteForceNeighbors as BruteForceNeighbors
from ._systems._neighbors import JaxMDNeighbors as JaxMDNeighbors
from ._systems._neighbors import minimum_image as minimum_image
from ._systems._neural_potential import NeuralPotential as NeuralPotential
from ._systems._pair_energies import AbstractPairEnergy as AbstractPairEnergy
from ._systems._pair_energies import Coulomb as Coulomb
from ._systems._pair_energies import LennardJones as LennardJones
from ._systems._pair_energies import Morse as Morse
from ._systems._potential import AbstractPotential as AbstractPotential
from ._systems._potential import PotentialFunction as PotentialFunction
from ._systems._potential import UniformGravity as UniformGravity
from ._systems._rigid_bodies import RigidBodies as RigidBodies
from ._systems._rigid_body import RigidBody as RigidBody
from ._systems._rigid_body import heavy_top as heavy_top
from ._systems._rigid_rotors import RigidRotors as RigidRotors
from ._systems._se3_body import RigidBodySE3 as RigidBodySE3
from ._systems._se3_potentials import CentralGravity as CentralGravity
from ._systems._se3_potentials import UniformGravitySE3 as UniformGravitySE3
from ._systems._se3_potentials import full_body_problem as full_body_problem
from ._world import WorldState as WorldState
from ._world import state_from_world as state_from_world
from ._world import state_to_world as state_to_world

try:
    __version__ = _metadata.version("lievi")
except _metadata.PackageNotFoundError:  # running from a source tree that is not installed
    __version__ = "0.0.0+unknown"


def __getattr__(name: str):
    # Old names kept for one release, with a warning (CHANGELOG, "Deprecated").
    if name == "has_fast_path":
        import warnings

        warnings.warn(
            "`lievi.has_fast_path` is deprecated: it is `lievi.advanced.has_fast_path` (an "
            "implementation detail, with the other knobs in `lievi.advanced`); use that name.",
            DeprecationWarning,
            stacklevel=2,
        )
        return advanced.has_fast_path
    if name == "InertiaFit":
        import warnings

        warnings.warn(
            "`lievi.InertiaFit` is deprecated: it is `lievi.SystemFit` (the result of "
            "`fit_system` and `fit_inertia`); use that name.",
            DeprecationWarning,
            stacklevel=2,
        )
        return SystemFit
    raise AttributeError(f"module 'lievi' has no attribute {name!r}")


# The public API is exactly the explicit re-exports above (`from ._x import Y as Y`);
# tests/test_docs.py checks this and that each has an entry in the API reference.
__all__ = sorted(name for name in dir() if not name.startswith("_"))
