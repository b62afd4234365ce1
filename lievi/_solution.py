"""`Solution`: a computed trajectory, as `simulate` and `simulate_batch` return it."""

from __future__ import annotations

import equinox as eqx
import jax
from jaxtyping import Array, Float, Int

from ._systems._base import AbstractLieSystem


class Solution(eqx.Module):
    """A computed trajectory.

    **Attributes:**

    - `ts`: saved times, shape `(T,)`, `T = n_steps // save_every + 1` (initial state included).
    - `g`: group elements, shape `(T, n, n)`.
    - `m`: momenta in algebra coordinates (body momentum `Π` for left-invariant systems,
      spatial `μ` for right-invariant ones), shape `(T, d)`.
    - `result`: a `RESULTS` code for the whole run (the first failure, if any). After a
      failed step the state is NaN, so no number past a failure can be mistaken for a result.
    - `stats`: `newton_iterations` and `residual`, shape `(T − 1,)`, the maximum over the
      steps between consecutive saves; `failed_step`, the index of the first failed step
      (−1 if none); `total_newton_iterations`; `num_steps`.
    - `advected`: the advected parameter `Γ = gᵀa` of the system's potential (gravity's
      vertical in the body frame for `UniformGravity`; paper §7), shape `(T, n)`, when the
      potential has one and `Save.g` or `Save.advected`, else `None`.
    """

    ts: Float[Array, " T"]
    g: Float[Array, "T n n"] | None
    m: Float[Array, "T d"] | None
    result: Int[Array, ""]
    stats: dict[str, Array]
    advected: Float[Array, "T n"] | None = None

    def angular_velocity(
        self, system: AbstractLieSystem, frame: str = "body"
    ) -> Float[Array, "T d"]:
        """Angular velocity along the trajectory (frames: docs/theory/conventions.md).

        **Arguments:**

        - `system`: the system that was simulated (its inverse Legendre map turns momentum
          into velocity; for the rigid body `Ω = I⁻¹Π`).
        - `frame`: `"body"` for `Ω = g⁻¹ġ` (body coordinates), `"spatial"` for
          `ω = ġg⁻¹` (world coordinates; `ω = gΩ` on SO(3)).

        **Returns:** algebra coordinates, shape `(T, d)` (any leading batch axes of a batched
        `Solution` kept).
        """
        if frame not in ("body", "spatial"):
            raise ValueError(f"`frame` must be 'body' or 'spatial', got {frame!r}.")
        xi = _over_leading_axes(system.velocity, len(system.momentum_shape()), self.m)
        # Left-invariant systems carry the body velocity, right-invariant the spatial one.
        if frame != system.side.carried_frame():
            xi = system.side.other_frame(system.group, self.g, xi)
        return xi

    def spatial_momentum(self, system: AbstractLieSystem) -> Float[Array, "T d"]:
        """The momentum conserved by the symmetry, along the trajectory: `gΠ` on SO(3).

        Left-invariant systems: the spatial momentum `Ad*_{g⁻¹}Π = Ad_{g⁻¹}ᵀΠ` (`gΠ̂gᵀ` on
        SO(n)). Right-invariant systems: the body momentum `Ad_gᵀμ`. Conserved by the free
        flow and kept to round-off by the geometric integrators; the same quantity as
        `lievi.diagnostics.spatial_momentum`.

        **Arguments:**

        - `system`: the system that was simulated.

        **Returns:** shape `(T, d)` (leading batch axes kept).
        """
        return system.side.noether_momentum(system.group, self.g, self.m)


def _over_leading_axes(fn, core_ndim: int, x):
    for _ in range(x.ndim - core_ndim):
        fn = jax.vmap(fn)
    return fn(x)


def advected_of(system, g):
    """`Γ = gᵀa` of the system's potential at `g` (any leading axes), or `None`."""
    if system.potential is None or system.potential.advected_direction() is None:
        return None
    return system.potential.advected(g)
