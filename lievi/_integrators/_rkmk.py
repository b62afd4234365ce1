"""A Lie-group Runge–Kutta method of order 4: Runge–Kutta–Munthe-Kaas (RKMK4).

The Euler–Poincaré equations with reconstruction (`_rk4.py`),

    left-invariant:   ṁ = ad_ξᵀ m + M(g),    ġ = g ξ̂;
    right-invariant:  ṁ = −ad_ξᵀ m + M(g),   ġ = ξ̂ g,

(`ξ` the velocity of `m`, `M` the potential's generalised force plus any external force)
are integrated with `g` written in the exponential chart about the step's start,
`g(t) = g_k exp(u(t))` (left; `exp(u(t)) g_k` right). Then `u` lives in the Lie algebra, a
vector space, and satisfies

    u̇ = dexp⁻¹_{−u}(ξ)   (left),      u̇ = dexp⁻¹_{u}(ξ)   (right),

with `dexp⁻¹` the inverse of the right-trivialised derivative of `exp`
(`MatrixLieGroup.dexpinv`). Classical RK4 on `(u, m)` from `u = 0`, and
`g_{k+1} = g_k exp(u_{k+1})`: the method of Munthe-Kaas (Hairer–Lubich–Wanner, *Geometric
Numerical Integration*, §IV.8.2). It is order 4 in `g` and `m` (`dexp⁻¹` is used exactly,
not truncated) and `g` stays on the group to round-off, because it only ever moves by
exponentials — unlike classical RK4 in the matrix embedding (`lievi.RK4`), whose `g` drifts
off the group. It is neither symplectic nor Lie–Poisson: the Casimirs and the energy drift
at O(h⁴) per unit time, as RK4's do.

Chosen over Crouch–Grossman and commutator-free methods because it needs only the group's
`exp` and `dexpinv` (closed forms on SO(3) and SE(3), generic ones on any matrix group),
one exponential per step, and works unchanged on both sides and with any force.

Fast paths (`kernels`): the rigid body with principal moments on SO(3) and any body on
SE(3) (`RigidBodySE3`), free or in a potential linear in `g` (uniform gravity).
"""

from __future__ import annotations

import dataclasses
import math

import jax.numpy as jnp
from jaxtyping import Scalar

from .._checks import check_shape
from .._kernels._base import kernels_enabled
from .._kernels._rkmk import RKMK4Kernel
from .._kernels._rkmk_se3 import RKMK4SE3Kernel
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractIntegrator, StepInfo
from ._rk4 import momentum_rate


class RKMK4(AbstractIntegrator):
    """Runge–Kutta–Munthe-Kaas of order 4: classical RK4 in the exponential chart of the
    group about each step's start (module docstring). Works for any `AbstractLieSystem`
    (either side, potentials, forcing); `g` stays on the group to round-off. Explicit, no
    arguments. Not symplectic: energy and Casimirs drift at O(h⁴) per unit time.
    """

    def order(self) -> int:
        return 4

    def step_bound(self) -> float:
        # RK4's stability on the imaginary axis (rotation at rate |Ω|): |R(iy)| ≤ 1 iff
        # y ≤ 2√2 (< π, so `u` also stays inside the exponential's injectivity radius).
        return 2 * math.sqrt(2)

    def kernels(self):
        # Closed forms for the rigid body with principal moments (`_kernels/_rkmk.py`) and
        # for any body on SE(3) (`_kernels/_rkmk_se3.py`).
        return RKMK4Kernel(), RKMK4SE3Kernel()

    def batch_kernel(self, system: AbstractLieSystem, batched: bool = False):
        # With a potential linear in `g` (gravity) the same kernels take its wrench per stage.
        if system.potential is None:
            return self.free_kernel(system, batched)
        if not kernels_enabled() or not self._kernels_compute_step():
            return None
        for kernel in self.kernels():
            kernel = dataclasses.replace(kernel, potential=system.potential)
            if kernel.physics(system, batched) is not None:
                return kernel
        return None

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        group, side = system.group, system.side
        n, d = group.matrix_dim, group.algebra_dim
        check_shape("g", g, (n, n), f"a {n}×{n} group element")
        check_shape("m", m, (d,), f"momentum coordinates of dimension {d}")
        # The kernel integrates the unforced body (free or in gravity): otherwise the field.
        kernel = None if force is not None else self.batch_kernel(system)
        if kernel is not None:
            g_next, m_next, result, iterations, residual = kernel.one_body_step(system, g, m, h)
            return g_next, m_next, StepInfo(result, iterations, residual)

        def f(s, u, mm):
            # The chart about g_k: g = g_k exp(u) (left) or exp(u) g_k (right).
            gg = side.compose(group, g, group.exp(u))
            xi = system.velocity(mm)
            u_dot = group.dexpinv(-side.sign * u) @ xi
            return u_dot, momentum_rate(system, gg, mm, xi, force, s)

        u0 = jnp.zeros(d, m.dtype)
        k1 = f(t, u0, m)
        k2 = f(t + h / 2, h / 2 * k1[0], m + h / 2 * k1[1])
        k3 = f(t + h / 2, h / 2 * k2[0], m + h / 2 * k2[1])
        k4 = f(t + h, h * k3[0], m + h * k3[1])
        u, m_next = (
            y + h / 6 * (a + 2 * b + 2 * c + e) for y, a, b, c, e in zip((u0, m), k1, k2, k3, k4)
        )
        g_next = side.compose(group, g, group.exp(u))
        finite = jnp.all(jnp.isfinite(m_next)) & jnp.all(jnp.isfinite(g_next))
        result = jnp.where(finite, RESULTS.successful, RESULTS.nonfinite)
        zero = jnp.zeros((), m_next.dtype)
        return g_next, m_next, StepInfo(result, jnp.zeros((), jnp.int32), zero)
