"""Classical Runge–Kutta 4 on the Euler–Poincaré equations: the non-geometric baseline.

The continuous equations (the ones `lievi.reference_solution` solves) are, with `ξ` the
velocity of `m` (inverse Legendre map),

    left-invariant:   ṁ = ad_ξᵀ m + M(g),    ġ = g ξ̂;
    right-invariant:  ṁ = −ad_ξᵀ m + M(g),   ġ = ξ̂ g,

with `M` the generalised force of the system's potential (zero for a free system;
`AbstractLieSystem.force`), plus any external force `f(t, g, m)` (`lievi.Control`,
`lievi.ForceLaw`; a held control is constant over the step).

RK4 treats `(g, m)` as a point of `R^{n×n} × R^d`: fourth order, explicit, and nothing
else. `g` drifts off the group, the momentum off its coadjoint orbit (Casimirs drift) and
the energy drifts — slowly, O(h⁴) per unit time, but without bound, which is what the
structure-preserving methods are compared against (the tests measure it over T = 1e4).
"""

from __future__ import annotations

import math

import jax
import jax.numpy as jnp
from jaxtyping import Scalar

from .._checks import check_shape
from .._kernels._explicit import RK4Kernel
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractIntegrator, StepInfo


def momentum_rate(system: AbstractLieSystem, g, m, xi, force=None, t=0.0):
    """`ṁ = ± ad_ξᵀ m + M(g) (+ force(t, g, m))`: the Euler–Poincaré equation (2.4)/(2.5)
    with the potential's generalised force and an external one (`None`: none), and the
    reaction of the system's constraints where it has any."""
    # `ad_ξᵀ m` per body where the state holds several (leading axes).
    ad = system.group.ad(xi)
    m_dot = system.side.coadjoint_sign() * jnp.einsum("...ba,...b->...a", ad, m)
    if system.potential is not None:
        m_dot = m_dot + system.force(g)
    if force is not None:
        m_dot = m_dot + jnp.asarray(force(t, g, m), m_dot.dtype)
    # A system with constraints adds their reaction (`AbstractLieSystem.constrained_rate`).
    return system.constrained_rate(g, m, m_dot)


def euler_poincare_vector_field(system: AbstractLieSystem, g, m, force=None, t=0.0):
    """`(ġ, ṁ)` of the Euler–Poincaré equations with reconstruction.

    `force`: an external generalised force `force(t, g, m)` added to `ṁ` (or `None`).
    """
    xi = system.velocity(m)
    g_dot = system.side.tangent(system.group, g, xi)
    return g_dot, momentum_rate(system, g, m, xi, force, t)


class RK4(AbstractIntegrator):
    """Classical fourth-order Runge–Kutta on the Euler–Poincaré equations (a baseline).

    Works for any `AbstractLieSystem` (left- or right-invariant). Not geometric: `g` leaves
    the group and Casimirs and energy drift (see the module docstring). No arguments.
    """

    def order(self) -> int:
        return 4

    def step_bound(self) -> float:
        # Stability of RK4 on the imaginary axis (rotation at rate |Ω|): |R(iy)| ≤ 1 iff
        # y ≤ 2√2; beyond it `g` and `m` grow geometrically (det g → −4e4 was seen).
        return 2 * math.sqrt(2)

    def own_step(self) -> bool:
        # The kernels and the step cache compute this class's own step (not a subclass's).
        return type(self) is RK4

    def kernels(self):
        return (RK4Kernel(),)

    def step(self, system: AbstractLieSystem, g, m, h: Scalar, force=None, t: Scalar = 0.0):
        system.check_unconstrained(type(self).__name__)
        check_shape("g", g, system.element_shape(), "the system's configuration")
        check_shape("m", m, system.momentum_shape(), "the system's momentum coordinates")
        # The kernel integrates the free, unforced body: otherwise the generic field.
        fast = None
        if force is None and system.potential is None:
            fast = self.kernel_step(system, g, m, h)
        if fast is not None:  # closed forms on components (the rigid body, principal moments)
            return fast

        def f(s, y):
            return euler_poincare_vector_field(system, *y, force=force, t=s)

        def axpy(a, k, y):
            return jax.tree.map(lambda ki, yi: yi + a * ki, k, y)

        y = (g, m)
        k1 = f(t, y)
        k2 = f(t + h / 2, axpy(h / 2, k1, y))
        k3 = f(t + h / 2, axpy(h / 2, k2, y))
        k4 = f(t + h, axpy(h, k3, y))
        g_next, m_next = jax.tree.map(
            lambda yi, a, b, c, e: yi + h / 6 * (a + 2 * b + 2 * c + e), y, k1, k2, k3, k4
        )
        finite = jnp.all(jnp.isfinite(m_next)) & jnp.all(jnp.isfinite(g_next))
        result = jnp.where(finite, RESULTS.successful, RESULTS.nonfinite)
        zero = jnp.zeros((), m_next.dtype)
        return g_next, m_next, StepInfo(result, jnp.zeros((), jnp.int32), zero)
