"""N interacting rigid rotors: a left-invariant system on the product group SO(3)ᴺ.

Each body `i` turns about its own pivot, a point fixed in space (and in the body): its
configuration is a rotation `R_i` and its momentum the body angular momentum `Π_i` about
the pivot. The state is `g` of shape `(N, 3, 3)` and `m` of shape `(N, 3)`. The kinetic
energy is block-diagonal, `l(Ω) = Σ_i ½ Ω_iᵀ J_i Ω_i` with `J_i` the inertia tensor about
the pivot, and a potential `V(R_1, …, R_N)` couples the bodies (paper §7: a potential on
the group, here the product group). The Euler–Poincaré equations are each body's Euler
equations driven by its own torque,

    Π̇_i = Π_i × Ω_i + M_i(g),     Ṙ_i = R_i Ω̂_i,

with `M_i(g) = −d/dε V(…, R_i exp(ε e_a), …)` the body-frame torque on body `i`, by
autodiff of `V` as for one body (`AbstractLieSystem.force`).

A kick integrator steps them as kick (all bodies) – free step of each body – kick (all
bodies): the discrete Lagrangian `Σ_i L_d^i − (h/2)(V(g_k) + V(g_{k+1}))` of the product
gives, as for one body, the half kicks of the DLP step (3.3) around the free step, and the
free step of the product is the product of the free steps: each body's own free step as
`lievi.RigidBody(J_i)` — the DEP step (4.8), Moser–Veselov's, the splitting's — run on the
N bodies at once (`free_flow`, `jax.vmap`). With `N = 1` it is `RigidBody`'s step.

Symmetry: a potential of the relative rotations, `V(Q R_1, …, Q R_N) = V(R_1, …, R_N)` for
every `Q ∈ SO(3)`, leaves the Lagrangian invariant under the diagonal left action of SO(3)
on SO(3)ᴺ; its momentum map is the total spatial angular momentum `Σ_i R_i Π_i` (each
body's about its own pivot; `lievi.diagnostics.total_momentum`). The discrete Lagrangian
has the same invariance, so the discrete flow conserves it exactly (discrete Noether
theorem, paper §2): each free step conserves its body's `R_i Π_i`, and the kicks add
torques whose spatial sum `Σ R_i M_i` vanishes. A potential invariant only under the
rotations `Q` about an axis `a` conserves `a · Σ_i R_i Π_i` only.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import check_real_dtype
from .._groups._base import MatrixLieGroup
from .._groups._so3 import SO3
from ._base import AbstractLieSystem
from ._bodies import check_per_body_inertia, each_body, inertia_conditions, orthonormal_frame
from ._potential import AbstractPotential, as_potential
from ._rigid_body import RigidBody
from ._side import Side


class RigidRotors(AbstractLieSystem):
    """N rigid bodies, each turning about its own fixed pivot, coupled by a potential: a
    left-invariant system on SO(3)ᴺ.

    **Arguments:**

    - `inertia`: principal moments `(N, 3)` or tensors `(N, 3, 3)`, each about its body's
      pivot, in the body frame (the parallel-axis theorem moves a tensor about the centre
      of mass there, as `lievi.heavy_top(..., inertia_about="center_of_mass")` does).
    - `potential`: `None` (N free rigid bodies), a `lievi.AbstractPotential` of the
      rotations `g` of shape `(N, 3, 3)` (`lievi.DipoleCoupling`), or any callable
      `V(g) -> scalar`; the torques are derived from it by autodiff.

    The state is `g` `(N, 3, 3)` (the rotations `R_i`) and `m` `(N, 3)` (the body angular
    momenta `Π_i` about the pivots); `simulate`, `simulate_batch` and the diagnostics take
    them as they take one body's. `lievi.diagnostics.total_momentum` gives the total
    spatial angular momentum `Σ R_i Π_i` (conserved for a coupling of the relative
    rotations), `lievi.diagnostics.energy` the kinetic plus the coupling energy. With
    `N = 1` the runs equal those of `RigidBody(inertia[0], potential=…)`.
    """

    inertia: Float[Array, "N 3"] | Float[Array, "N 3 3"]
    potential: AbstractPotential | None
    principal: bool = eqx.field(static=True)
    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)

    def __init__(self, inertia, potential=None):
        check_real_dtype("inertia", inertia)
        inertia = jnp.asarray(inertia)
        check_per_body_inertia(inertia)
        self.inertia = inertia
        # Moments or tensors, fixed now: a batch of systems built with `jax.vmap` has
        # leading axes that would make `(B, N, 3)` moments look like `(N, 3, 3)` tensors.
        self.principal = inertia.ndim == 2
        self.potential = as_potential(potential)
        self.group = SO3
        self.side = Side.LEFT

    @property
    def n_bodies(self) -> int:
        return jnp.shape(self.inertia)[-2 if self.principal else -3]

    def element_shape(self):
        return (self.n_bodies, 3, 3)

    def momentum_shape(self):
        return (self.n_bodies, 3)

    def parameter_conditions(self):
        """Finite, each inertia tensor symmetric positive definite and not singular to
        rounding (`inertia_conditions`)."""
        return super().parameter_conditions() + inertia_conditions("inertia", self.inertia_tensor)

    @property
    def inertia_tensor(self) -> Float[Array, "N 3 3"]:
        """The inertia tensors `J_i` about the pivots, `(…, N, 3, 3)` (any leading axes of
        a batch of systems built with `jax.vmap` kept)."""
        inertia = jnp.asarray(self.inertia)
        if not self.principal:
            return inertia
        return inertia[..., None] * jnp.eye(3, dtype=inertia.dtype)

    def free_flow(self, integrator, g, m, h: Scalar):
        """Each body's free step by `integrator`: its `free_step` of the free rigid body
        `RigidBody(J_i)` (the same code as for one body, its fast path included), the N
        bodies at once (`jax.vmap`), each rotation then kept orthogonal and its body
        momentum read off the conserved spatial one (`_bodies.orthonormal_frame`, as for
        `lievi.RigidBodies`). The step's report is that of the worst body
        (`_bodies.worst_body_report`)."""

        def one(index, J, g, m):
            # The integrator with its per-run data of this body, if any.
            R, Pi, info = integrator.body(index).free_step(RigidBody(J), g, m, h)
            R, Pi = orthonormal_frame(R, R @ Pi)
            return R, Pi, info

        return each_body(one, jnp.arange(self.n_bodies), self.inertia, g, m)

    def principal_frames(self):
        """Each body's `RigidBody.principal_frames`, the body axis leading: computed once
        per run by a method that steps in the principal frame
        (`lievi.LiePoissonSplitting`)."""
        return jax.vmap(lambda J: RigidBody(J).principal_frames())(jnp.asarray(self.inertia))

    def free_discrete_lagrangian(self, integrator, g0, g1, h: Scalar) -> Scalar:
        """`Σ_i L_d^i(R0_i, R1_i)`: each body's discrete Lagrangian as the free rigid body
        `RigidBody(J_i)`, the body `free_flow` steps."""

        def one(J, a, b):
            return integrator.kinetic_discrete_lagrangian(RigidBody(J), a, b, h)

        return jnp.sum(jax.vmap(one)(self.inertia, g0, g1))

    def lagrangian(self, xi: Float[Array, "N 3"]) -> Scalar:
        return jnp.sum(xi * self.legendre(xi)) / 2

    def legendre(self, xi: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        inertia = jnp.asarray(self.inertia)
        if self.principal:
            return inertia * xi
        return jnp.einsum("nij,nj->ni", inertia, xi)

    def velocity(self, m: Float[Array, "N 3"]) -> Float[Array, "N 3"]:
        inertia = jnp.asarray(self.inertia)
        if self.principal:
            return m / inertia
        return jnp.linalg.solve(inertia, m[..., None])[..., 0]

    def energy(self, m: Float[Array, "N 3"]) -> Scalar:
        """The kinetic energy `Σ_i ½ Π_iᵀ J_i⁻¹ Π_i` (`lievi.diagnostics.energy` adds `V`)."""
        return jnp.sum(m * self.velocity(m)) / 2
