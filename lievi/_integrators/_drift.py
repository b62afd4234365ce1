"""A free rigid body in vacuum stepped by a method of its rotation alone, plus its drift.

For a body in vacuum with its origin at the centre of mass (kinetic tensor `diag(J, m1)`)
the free Hamiltonian on `se(3)*` is

    H(Π, P) = ½ Πᵀ J⁻¹ Π + |P|²/(2m),

and `|P|²` is a Casimir of `se(3)*` (`lievi.SE3.casimirs`): the flow of `|P|²/(2m)`, the
uniform translation `p ← p + t R P/m` at the constant spatial linear momentum `RP` (the
body momentum `(Π, P)` unchanged), commutes with every other flow. So the free step of
the body is any step of the rotation `(R, Π)` — the free rigid body `RigidBody(J)` on
SO(3), with `P` carried along as `P_{k+1} = F_kᵀ P_k` by the same increment `F_k` — composed
with the exact translation over the step. The composition has the rotation method's order
and symmetry, and conserves what it conserves: the spatial angular momentum
`RΠ + p × RP` changes only by `(h RP/m) × RP = 0` in the translation.

This is how `lievi.LiePoissonSplitting` and `lievi.MoserVeselov`, methods of the rotation
group, step each body of `lievi.RigidBodies`.
"""

from __future__ import annotations

import jax.numpy as jnp
from jaxtyping import Scalar

from .._groups._se3 import SE3
from .._systems._bodies import orthonormal_frame
from .._systems._rigid_body import RigidBody


def rotation_and_drift_lagrangian(integrator, inertia, mass, g0, g1, h: Scalar):
    """The discrete Lagrangian of `rotation_and_drift`: `integrator`'s kinetic discrete
    Lagrangian of `RigidBody(inertia)` on the rotations, plus the exact one of the uniform
    translation, `mass |p_1 − p_0|² / (2h)` (the action of the straight line from `p_0` to
    `p_1` in time `h`). Its discrete Euler–Lagrange equations (paper (2.1)) in the
    rotation are the method's; in the position, `m (p_1 − 2p_0 + p_{−1})/h = 0` with
    the kicks' forces, the drift at constant spatial linear momentum."""
    kinetic = integrator.kinetic_discrete_lagrangian(
        RigidBody(inertia), SE3.rotation(g0), SE3.rotation(g1), h
    )
    step = SE3.translation(g1) - SE3.translation(g0)
    return kinetic + mass * jnp.sum(step**2) / (2 * h)


def rotation_and_drift(integrator, inertia, mass, g, m, h: Scalar):
    """`integrator`'s free step of `RigidBody(inertia)` on `(R, Π)`, `P` turned with `R`,
    and the exact translation `p ← p + h R_k P_k / mass`. Returns `(g, m, StepInfo)`."""
    R, p = SE3.rotation(g), SE3.translation(g)
    Pi, P = m[:3], m[3:]
    R_next, Pi_next, info = integrator.free_step(RigidBody(inertia), R, Pi, h)
    # The spatial momenta `RΠ` (kept by the rotation step) and `RP` (constant).
    angular, linear = R_next @ Pi_next, R @ P
    p_next = p + h * linear / mass
    # The rotation kept orthogonal, the body momenta read off the spatial ones with it
    # (`_bodies.orthonormal_frame` says why).
    R_next, Pi_next, P_next = orthonormal_frame(R_next, angular, linear)
    m_next = jnp.concatenate([Pi_next, P_next])
    return SE3.from_rotation_translation(R_next, p_next), m_next, info
