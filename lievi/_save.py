"""What a run stores and how often: one object (`Save`), as diffrax's `SaveAt`."""

from __future__ import annotations

import warnings

import equinox as eqx
import numpy as np


class Save(eqx.Module):
    """What every run function stores, and how often; the fields not stored are `None` in
    the `Solution` (`failed_step`, `total_newton_iterations` and `num_steps` are always
    kept). The default, `Save()`, stores `g`, `m` and the statistics at every step.

    **Arguments:**

    - `g`: the group elements `(…, T, n, n)`. Also picks the algorithm of a system whose
      potential has an advected parameter (e.g. `UniformGravity`): without `g` the fast
      path carries the reduced state `(Π, Γ)` of the paper's §7 instead of `(Π, g)`.
    - `m`: the momenta `(…, T, d)`.
    - `stats`: the per-save Newton statistics (`newton_iterations`, `residual`).
    - `advected`: the advected parameter `Γ_k = g_kᵀa` (`Solution.advected`), also given
      whenever `g` is saved.
    - `every`: save every this many steps (as diffrax's `SaveAt(steps=...)`); it must
      divide `n_steps`. A run keeps `n_steps // every + 1` saves (the initial state
      included); `every=n_steps` keeps the initial and the final state only.
    """

    g: bool = eqx.field(default=True, static=True)
    m: bool = eqx.field(default=True, static=True)
    stats: bool = eqx.field(default=True, static=True)
    advected: bool = eqx.field(default=False, static=True)
    every: int = eqx.field(default=1, static=True)

    def __check_init__(self):
        every = self.every
        if isinstance(every, bool) or not isinstance(every, (int, np.integer)) or every < 1:
            raise ValueError(f"`Save.every` must be an integer ≥ 1, got {every!r}.")
        for name in FIELDS:
            if not isinstance(getattr(self, name), bool):
                raise ValueError(
                    f"`Save.{name}` must be True or False, got {getattr(self, name)!r}."
                )

    def names(self) -> tuple[str, ...]:
        """The saved fields' names, e.g. `("g", "m", "stats")`."""
        return tuple(name for name in FIELDS if getattr(self, name))

    def with_advected(self) -> bool:
        """Whether `Solution.advected` is given (`advected`, or `g` to read it from)."""
        return self.advected or self.g


FIELDS = ("g", "m", "stats", "advected")


def as_save(save, save_every=None, label: str = "this run") -> Save:
    """`save` as a `Save`; the spellings of earlier releases, a sequence of field names and
    a separate `save_every` (overriding `save.every`), with a `DeprecationWarning`."""
    if not isinstance(save, Save):
        if not isinstance(save, (tuple, list)):
            raise ValueError(
                f"`save` must be a `lievi.Save`, e.g. lievi.Save(every=10, stats=False); "
                f"got {save!r}."
            )
        names = tuple(save)
        unknown = set(names) - set(FIELDS)
        if unknown:
            raise ValueError(f"`save` may only contain {FIELDS}, got {sorted(unknown)}.")
        keywords = {name: name in names for name in FIELDS}
        spelled = ", ".join(f"{name}={value}" for name, value in keywords.items())
        deprecated(label, f"`save={names!r}`", f"`save=lievi.Save({spelled})`")
        save = Save(**keywords)
    if save_every is not None:
        deprecated(label, "`save_every=`", f"`save=lievi.Save(every={save_every!r})`")
        save = Save(save.g, save.m, save.stats, save.advected, save_every)
    return save


def deprecated(label: str, old: str, new: str) -> None:
    """A `DeprecationWarning` pointing at the call of the run function `label` (user → run
    function → `options` → reader → here)."""
    warnings.warn(
        f"{label}: {old} is deprecated and will be removed in the next release; pass {new}.",
        DeprecationWarning,
        stacklevel=5,
    )
