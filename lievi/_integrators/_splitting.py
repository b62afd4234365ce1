"""The explicit Lie–Poisson splitting of the free rigid body (paper §6).

The Hamiltonian of the (generalized) rigid body in principal coordinates is a sum of
exactly integrable pieces,

    H(Π) = Σ_p H_p,   H_p = Π_p² / (2 I_p),

one per body axis on SO(3) (`I_p` the principal moments) and one per coordinate plane
`(i, j)` on SO(n) (`I_p = Λᵢ + Λⱼ`). The flow of `H_p` is a steady rotation about that
axis / in that plane: `Π_p` is constant, the velocity is `ξ = (Π_p/I_p) e_p`, and for a
duration `t`

    F = exp(t Π_p/I_p · e_p)   (a Givens rotation),   g ← g F,   Π̂ ← Fᵀ Π̂ F.

Each sub-flow is the exact flow of a left-invariant Hamiltonian on T*SO(n), hence a Poisson
map on so(n)* (Casimirs kept to round-off) that conserves the spatial momentum `g Π̂ gᵀ` —
updating `g` by the same sub-rotation is the reconstruction the paper (§6) says splitting
methods lack in general. The step is the symmetric Strang composition

    Φ_h = φ¹_{h/2} ∘ … ∘ φ^{d−1}_{h/2} ∘ φ^d_h ∘ φ^{d−1}_{h/2} ∘ … ∘ φ¹_{h/2},

second order and symmetric (`Φ_{−h} ∘ Φ_h = id`), so it can be composed to higher order
(McLachlan 1993; Reich; Touma & Wisdom 1994). Explicit: no solve, no iterations.

The pieces are taken in the order of the coordinates: the principal axes as given on
SO(3), the planes in `lievi.SOn`'s order on SO(n); a full inertia tensor's principal axes
in ascending order of the moments (`jnp.linalg.eigh`). The order changes the O(h³) local
error, not the order or the conserved quantities.

A full inertia tensor is diagonalised first (`I = Q D Qᵀ`, `Q ∈ SO(3)`), the state is
rotated into the principal frame (`g Q`, `Qᵀ Π`), stepped, and rotated back. A run
diagonalises once, in its set-up (`LiePoissonSplitting.init`: the frames are carried into
the loop as data); a step taken alone does it at every call. The derivative of the
eigendecomposition is undefined for repeated moments: to differentiate with respect to
the inertia of a symmetric body, pass principal moments.
"""

from __future__ import annotations

import dataclasses
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Scalar

from .._checks import check_shape
from .._groups._son import planes
from .._kernels._explicit import SplittingKernel
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractKickIntegrator, StepInfo
from ._drift import rotation_and_drift
from ._moser_veselov import check_pair_sums, check_rigid_body


def _sub_flow(carry, x):
    """Exact flow of `H_p` for a time `t`: `g ← g F`, `Π̂ ← Fᵀ Π̂ F`, `F = exp(t Π_p/I_p · ê_p)`.

    `ê_p[j, i] = sign`, `ê_p[i, j] = −sign` (the basis of `lievi.SOn`), so `F` is the Givens
    rotation with `F[i, i] = F[j, j] = cos`, `F[j, i] = sign·sin`, `F[i, j] = −sign·sin`.
    Built from one-hot vectors so that one `lax.scan` body serves every plane: the
    compile time does not grow with the number of planes (unrolling 19 sub-flows on SO(5)
    compiled 4× slower, and its Jacobian 5× slower).
    """
    g, M = carry
    i, j, sign, t, moment = x
    eye = jnp.eye(g.shape[-1], dtype=g.dtype)
    e_i, e_j = eye[i], eye[j]
    angle = t * sign * (e_j @ M @ e_i) / moment  # Π_p = sign·Π̂[j, i] is constant on the flow
    c, s = jnp.cos(angle), sign * jnp.sin(angle)
    F = (
        eye
        + (c - 1) * (jnp.outer(e_i, e_i) + jnp.outer(e_j, e_j))
        + s * (jnp.outer(e_j, e_i) - jnp.outer(e_i, e_j))
    )
    return (g @ F, F.T @ M @ F), None


class LiePoissonSplitting(AbstractKickIntegrator):
    """Explicit symmetric (Strang) splitting of the rigid-body Hamiltonian (paper §6).

    Second order, symmetric, explicit; a Poisson map on `so(n)*` that keeps Casimirs and
    the spatial momentum to round-off and `g` on SO(n). Not variational in the sense of a
    discrete Lagrangian on `G × G` (no `discrete_lagrangian`), but each sub-step is an exact
    Hamiltonian flow, so the method is symplectic on `T*SO(n)`.

    Works for `RigidBody` (principal moments or a full tensor, diagonalised first) and
    `GeneralizedRigidBody` on SO(n) (one coordinate plane at a time).
    """

    # The system's principal moments, frames and principal bodies
    # (`AbstractLieSystem.principal_frames`), set by `init` for a run, per body for a
    # system of several bodies (`body`); `None`: each step computes them (two
    # eigendecompositions and determinants per body, in every step and its derivative).
    frames: Any = None

    def order(self) -> int:
        return 2

    def is_symmetric(self) -> bool:
        # A palindromic (Strang) product of exact flows: Φ_{−h} = Φ_h⁻¹.
        return True

    def free_body_step(self, inertia, mass, g, m, h: Scalar):
        # A method of the rotation: the body's rotation by it, its translation exactly.
        return rotation_and_drift(self, inertia, mass, g, m, h)

    def own_step(self) -> bool:
        # The kernels and the step cache compute this class's own step (not a subclass's).
        return type(self) is LiePoissonSplitting

    def init(self, system: AbstractLieSystem, m0, h: Scalar):
        # The principal frames once per run, for a system with a full inertia tensor: the
        # step's derivative then runs through one eigendecomposition, not one per step.
        frames = system.principal_frames()
        if frames is None or frames[2] is None:
            return self
        return dataclasses.replace(self, frames=frames)

    def body(self, index):
        if self.frames is None:
            return self
        return dataclasses.replace(self, frames=jax.tree.map(lambda x: x[index], self.frames))

    def kernels(self):
        return (SplittingKernel(),)

    def free_step(self, system: AbstractLieSystem, g, m, h: Scalar):
        check_rigid_body("LiePoissonSplitting", system)
        check_pair_sums("LiePoissonSplitting", system)
        group = system.group
        n, d = group.matrix_dim, group.algebra_dim
        check_shape("g", g, (n, n), f"an element of SO({n})")
        check_shape("m", m, (d,), f"momentum coordinates of so({n})*")
        fast = self.kernel_step(system, g, m, h)
        if fast is not None:  # closed forms on components (the rigid body, principal moments)
            return fast
        if self.frames is None:
            moments, Q = system.principal_planes()
            principal = None if Q is None else system.principal_body()
        else:
            moments, Q, principal = self.frames
        if principal is not None:
            # A full tensor: the same step in its principal frame, `(g Q, Qᵀ Π)`, and back.
            # There the principal moments make it the closed-form kernel's (five sub-flows
            # as one quaternion product, a hand-written tangent) rather than five 3×3
            # rotations in a loop: for `RigidBodies`, whose point-mass tensors are full,
            # the forward run of 256 binaries took 0.75× the time (same run).
            principal_step = dataclasses.replace(self, frames=None).free_step
            g_next, m_next, info = principal_step(principal, g @ Q, Q.T @ m, h)
            return g_next @ Q.T, Q @ m_next, info
        if Q is not None:  # a system with a principal frame but no `principal_body`
            g, m = g @ Q, Q.T @ m
        i, j, sign = planes(n)
        last = d - 1
        # The palindrome p = 0 … d−2 (h/2), d−1 (h), d−2 … 0 (h/2).
        order = np.r_[np.arange(last), last, np.arange(last)[::-1]]
        fraction = np.r_[np.full(last, 0.5), 1.0, np.full(last, 0.5)]
        dtype = jnp.result_type(g, m)
        sequence = (
            jnp.asarray(i[order]),
            jnp.asarray(j[order]),
            jnp.asarray(sign[order], dtype),
            (jnp.asarray(fraction, dtype) * h).astype(dtype),
            jnp.asarray(moments, dtype)[order],
        )
        (g, M), _ = jax.lax.scan(_sub_flow, (g, group.hat(m)), sequence)
        m_next = group.vee(M)
        if Q is not None:
            g, m_next = g @ Q.T, Q @ m_next
        finite = jnp.all(jnp.isfinite(m_next)) & jnp.all(jnp.isfinite(g))
        result = jnp.where(finite, RESULTS.successful, RESULTS.nonfinite)
        zero = jnp.zeros((), m_next.dtype)
        return g, m_next, StepInfo(result, jnp.zeros((), jnp.int32), zero)
