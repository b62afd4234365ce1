"""What a batched run stores at each save: one object (`Save`), as diffrax's `SaveAt`."""

from __future__ import annotations

from collections.abc import Sequence

import equinox as eqx


class Save(eqx.Module):
    """Which per-save fields `lievi.simulate_batch` stores; the others are `None` in the
    `Solution` (the summary statistics `failed_step`, `total_newton_iterations` and
    `num_steps` are always kept). Storing nothing but the final state is what makes very
    large batches fit in memory.

    **Arguments:**

    - `g`: the group elements `(B, T, n, n)`. Also picks the algorithm of a system whose
      potential has an advected parameter (e.g. `UniformGravity`): without `g` the fast
      path carries the reduced state `(Π, Γ)` of the paper's §7 instead of `(Π, g)`.
    - `m`: the momenta `(B, T, d)`.
    - `stats`: the per-save Newton statistics (`newton_iterations`, `residual`).
    - `advected`: the advected parameter `Γ_k = g_kᵀa` (`Solution.advected`), also given
      whenever `g` is saved.

    `simulate_batch(save=("g", "m"))` — a sequence of these names — is the same as
    `save=Save(g=True, m=True, stats=False)`.
    """

    g: bool = eqx.field(default=True, static=True)
    m: bool = eqx.field(default=True, static=True)
    stats: bool = eqx.field(default=True, static=True)
    advected: bool = eqx.field(default=False, static=True)

    def __check_init__(self):
        for name in ("g", "m", "stats", "advected"):
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


def as_save(save: Save | Sequence[str]) -> Save:
    """`save` as a `Save`: itself, or from a sequence of field names (`ValueError` for a
    string or an unknown name)."""
    if isinstance(save, Save):
        return save
    if isinstance(save, str):
        raise ValueError(
            f"`save` must be a `lievi.Save` or a sequence of field names, e.g. ('g', 'm'), "
            f"got the string {save!r}."
        )
    save = tuple(save)
    unknown = set(save) - set(FIELDS)
    if unknown:
        raise ValueError(f"`save` may only contain {FIELDS}, got {sorted(unknown)}.")
    return Save(**{name: name in save for name in FIELDS})
