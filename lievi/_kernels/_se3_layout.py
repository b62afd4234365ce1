"""The state layout of the SE(3) kernels (`_se3.py`, `_se3_dense.py`, `_rkmk_se3.py`):
a free body on SE(3) with a 6×6 kinetic tensor, its pose as the 12 entries of `[R | p]`
and its momentum as the 6 of `m = (Π, P)`."""

from __future__ import annotations

import jax.numpy as jnp

from .._groups._se3 import SE3
from ._base import AbstractBatchKernel
from ._soa import component_major, dot, matrix


class SE3Kernel(AbstractBatchKernel):
    """The layout of a kernel for `RigidBodySE3` with a 6×6 kinetic tensor `M` (left
    side): its state the 12 entries of `[R | p]` and the 6 of `m = (Π, P)`; by default its
    constants the 36 entries of `M` and those of `M⁻¹` (`constants`)."""

    def physics(self, system, batched: bool = False):
        # A left-invariant system on `SE3` with a quadratic Lagrangian `½ξᵀMξ`: its 6×6 `M`.
        tensor = system.kinetic_tensor()
        if system.group != SE3 or system.side != "left" or tensor is None:
            return None
        return tensor if jnp.shape(tensor)[batched:] == (6, 6) else None

    def turn_rates(self, constants, h):
        # |h| times the rotation rows of M⁻¹ (`SE3.exp_norm`: the rotation part of M⁻¹m),
        # one operation on the whole block (`component_major`).
        Minv = matrix(constants[1])[..., :3, :]
        return component_major(jnp.abs(jnp.asarray(h))[..., None, None] * Minv)

    def turn_squared(self, rates, m):
        omega = tuple(sum(rates[i][j] * m[j] for j in range(6)) for i in range(3))
        return dot(omega, omega)

    def carried(self, g0):
        return tuple(g0[:, i, j] for i in range(3) for j in range(4))

    def elements(self, entries):
        # (…, 12, B) → (B, …, 4, 4), the last row (0, 0, 0, 1).
        top = jnp.moveaxis(entries, -1, 0).reshape(entries.shape[-1:] + entries.shape[:-2] + (3, 4))
        last = jnp.broadcast_to(jnp.eye(4, dtype=top.dtype)[3], top.shape[:-2] + (1, 4))
        return jnp.concatenate([top, last], axis=-2)
