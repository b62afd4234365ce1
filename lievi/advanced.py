"""Implementation knobs: how a run is computed, never what it computes.

- `Tuning`: passed as `tuning=` to any run function (`lievi.simulate`,
  `simulate_batch`, `stream_batch`, `simulate_with_neighbor_list`): the
  structure-of-arrays kernel on or off, its fixed Newton iterations, loop unrolling.
- `has_fast_path`: whether an integrator has a kernel for a system.

The defaults suit almost every run; these are for benchmarking and for tuning a device.
"""

from ._options import Tuning as Tuning
from ._simulate_batch import has_fast_path as has_fast_path

__all__ = ["Tuning", "has_fast_path"]
