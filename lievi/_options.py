"""The options every run function takes, with one set of defaults, checked in one place.

`lievi.simulate`, `simulate_batch`, `stream_batch` and `simulate_with_neighbor_list` take
the same keyword options (`OPTIONS`: what to save, `t0`, `throw`, `checkpoint`,
`progress_meter`, `forcing`, `args`, `monitor`, `tuning`) with the same defaults;
`options(...)` reads and checks them once for all. A run function that cannot honour an
option (a streamed run is not differentiated, so it has no `checkpoint`) names it in
`unsupported`: any value but the default is then a `ValueError` saying so.
"""

from __future__ import annotations

from typing import Any

import equinox as eqx

from ._checks import check_integer, check_scalar
from ._forcing import as_forcing
from ._monitor import as_monitor
from ._progress import as_progress_meter
from ._save import Save, as_save, deprecated
from ._scan import checkpoint_segment


class Tuning(eqx.Module):
    """How a run is computed, never what it computes: `lievi.advanced.Tuning`, passed as
    `tuning=` to any run function. The defaults suit almost every run.

    **Arguments:**

    - `fast`: use the integrator's structure-of-arrays kernel where it has one
      (`lievi.advanced.has_fast_path`); `False` runs the method's own step under
      `jax.vmap`. Both compute the same iterates to round-off.
    - `fixed_iterations`: (kernel) Newton iterations every body takes before the one
      convergence check; bodies still above tolerance then continue, alone, up to the
      integrator's `max_steps`. Default: the kernel's own (3 for the exp chart, 4 for the
      Cayley chart and Moser–Veselov; for one body, none: it stops at convergence). With
      `max_steps` equal to it there is no data-dependent loop; bodies not converged then
      are reported as failed.
    - `unroll`: steps per iteration of the compiled loop (`lax.scan`'s `unroll`). On a
      GPU a few steps per iteration amortise the per-iteration launch cost; it multiplies
      the compiled code, hence the compile time, by `unroll`.
    """

    fast: bool = eqx.field(default=True, static=True)
    fixed_iterations: int | None = eqx.field(default=None, static=True)
    unroll: int = eqx.field(default=1, static=True)

    def __check_init__(self):
        if not isinstance(self.fast, bool):
            raise ValueError(f"`Tuning.fast` must be True or False, got {self.fast!r}.")
        if self.fixed_iterations is not None:
            check_integer("Tuning.fixed_iterations", self.fixed_iterations, 1)
        check_integer("Tuning.unroll", self.unroll, 1)


# The common keyword options of every run function and their one set of defaults
# (tests/test_loop.py checks each run function's signature against it).
OPTIONS: dict[str, Any] = {
    "save": Save(),
    "t0": 0.0,
    "throw": True,
    "checkpoint": False,
    "progress_meter": False,
    "forcing": None,
    "args": None,
    "monitor": None,
    "tuning": Tuning(),
}
# Keywords of earlier releases, read with a `DeprecationWarning` for one release.
DEPRECATED = ("save_every", "fast", "fixed_iterations", "unroll")


class Options(eqx.Module):
    """The checked options of one run (`options`)."""

    n_steps: int = eqx.field(static=True)
    save: Save
    segment: int | None = eqx.field(static=True)
    progress: Any
    forcing: Any
    monitor: Any
    tuning: Tuning


def options(label: str, n_steps, given: dict, old: dict, unsupported=()) -> Options:
    """Read and check a run function's options once.

    `given`: the common options as passed (`OPTIONS`' names); `old`: the deprecated
    keywords passed (`DEPRECATED`; anything else is a `TypeError`, as Python's own);
    `unsupported`: options this run function cannot honour (`ValueError` unless default).
    """
    unknown = set(old) - set(DEPRECATED)
    if unknown:
        raise TypeError(f"{label}() got unexpected keyword arguments {sorted(unknown)}.")
    for name in unsupported:
        if given[name] is not OPTIONS[name] and not _equal(given[name], OPTIONS[name]):
            raise ValueError(f"{label} does not take `{name}` (pass the default).")
    n_steps = check_integer("n_steps", n_steps, 1)
    save = as_save(given["save"], old.get("save_every"), label)
    if n_steps % save.every:
        raise ValueError(
            f"`save.every` ({save.every}) must divide `n_steps` ({n_steps}); e.g. "
            f"lievi.Save(every={n_steps}) keeps the initial and the final state only."
        )
    check_scalar("t0", given["t0"])
    if not isinstance(given["throw"], bool):
        raise ValueError(f"`throw` must be True or False, got {given['throw']!r}.")
    return Options(
        n_steps,
        save,
        checkpoint_segment(given["checkpoint"], n_steps, save.every),
        as_progress_meter(given["progress_meter"], label),
        as_forcing(given["forcing"]),
        as_monitor(given["monitor"]),
        _tuning(label, given["tuning"], old),
    )


def _tuning(label: str, tuning, old: dict) -> Tuning:
    """`tuning`, with the deprecated keywords `fast`, `fixed_iterations`, `unroll` (as
    runs took them before `Tuning`) folded in."""
    if not isinstance(tuning, Tuning):
        raise ValueError(f"`tuning` must be a lievi.advanced.Tuning, got {tuning!r}.")
    knobs = {name: old[name] for name in ("fast", "fixed_iterations", "unroll") if name in old}
    if not knobs:
        return tuning
    spelled = ", ".join(f"{name}={value!r}" for name, value in knobs.items())
    deprecated(label, f"`{spelled}`", f"`tuning=lievi.advanced.Tuning({spelled})`")
    current = {name: getattr(tuning, name) for name in ("fast", "fixed_iterations", "unroll")}
    return Tuning(**{**current, **knobs})


def _equal(a, b) -> bool:
    try:
        return bool(a == b)
    except Exception:  # e.g. an array
        return False
