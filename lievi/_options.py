"""The options every run function takes (`OPTIONS`), with one set of defaults, read and
checked once for all by `options`."""

from __future__ import annotations

import dataclasses
from typing import Any

import equinox as eqx
import numpy as np

from ._checks import check_integer, check_scalar
from ._forcing import as_forcing
from ._monitor import as_monitor
from ._progress import as_progress_meter
from ._save import Save, as_save, deprecated


class Tuning(eqx.Module):
    """How a run is computed, never what it computes: `lievi.advanced.Tuning`, passed as
    `tuning=` to any run function. The defaults suit almost every run.

    **Arguments:**

    - `fast`: run a batch on the integrator's structure-of-arrays kernel as a batch
      (`lievi.advanced.has_fast_path`): fixed Newton iterations for every body, then the
      stragglers alone. `False` steps every body as a one-body `simulate` steps it, under
      `jax.vmap` (Newton to each body's convergence). Both compute the same iterates to
      round-off.
    - `fixed_iterations`: (kernel, `fast=True`) Newton iterations every body takes
      before the one convergence check; bodies still above tolerance then continue,
      alone, up to the integrator's `max_steps`. Default: the kernel's own (none for one
      body).
    - `unroll`: steps per iteration of the compiled loop (`lax.scan`'s `unroll`); it
      multiplies the compile time by `unroll`.
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
    """Read and check a run function's options: `given`, the common options as passed;
    `old`, the deprecated keywords passed (anything else is a `TypeError`, as Python's);
    `unsupported`, options the run function cannot honour (`ValueError` unless default)."""
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
    """`tuning`, with the deprecated keywords `fast`, `fixed_iterations`, `unroll` in."""
    if not isinstance(tuning, Tuning):
        raise ValueError(f"`tuning` must be a lievi.advanced.Tuning, got {tuning!r}.")
    knobs = {name: old[name] for name in DEPRECATED[1:] if name in old}
    if not knobs:
        return tuning
    spelled = ", ".join(f"{name}={value!r}" for name, value in knobs.items())
    deprecated(label, f"`{spelled}`", f"`tuning=lievi.advanced.Tuning({spelled})`")
    return dataclasses.replace(tuning, **knobs)


def _equal(a, b) -> bool:
    try:
        return bool(a == b)
    except Exception:  # e.g. an array
        return False


def checkpoint_segment(checkpoint, n_steps: int, save_every: int) -> int | None:
    """Steps per `jax.checkpoint`-ed segment (`checkpoint=`), or `None` for none."""
    if checkpoint is False or checkpoint is None:
        return None
    # A segment either lies inside one save interval or spans whole save intervals.
    n_saves = n_steps // save_every
    allowed = sorted(
        {d for d in range(1, save_every + 1) if save_every % d == 0}
        | {save_every * d for d in range(1, n_saves + 1) if n_saves % d == 0}
    )
    if checkpoint is True:
        # √N segments of √N steps minimise stored states + one segment's internals.
        return min(allowed, key=lambda c: abs(np.log(c) - 0.5 * np.log(n_steps)))
    if (
        isinstance(checkpoint, bool)
        or not isinstance(checkpoint, (int, np.integer))
        or checkpoint not in allowed
    ):
        raise ValueError(
            f"`checkpoint` must be True, False, or a segment length in steps that divides "
            f"`save_every` ({save_every}) or is a multiple of it dividing `n_steps` ({n_steps}); "
            f"got {checkpoint!r}. Pass checkpoint=True to choose one near √n_steps."
        )
    return int(checkpoint)
