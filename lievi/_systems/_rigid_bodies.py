"""N interacting rigid bodies: a left-invariant system on the product group SE(3)ᴺ.

Each body `i` has a pose `g_i = [[R_i, p_i], [0, 1]]` and a body-frame momentum
`m_i = (Π_i, P_i)`; the state is `g` of shape `(N, 4, 4)` and `m` of shape `(N, 6)`. The
kinetic energy is block-diagonal, `l(ξ) = Σ_i ½ ξ_iᵀ M_i ξ_i` with `M_i = diag(J_i, m_i 1)`,
and a potential `V(g_1, …, g_N)` couples the bodies. On the product group the
Euler–Poincaré equations with a potential (paper §7) are those of each body,

    ṁ_i = ad_{ξ_i}ᵀ m_i + M_i(g),     ġ_i = g_i ξ̂_i,

with `M_i(g) = −d/dε V(…, g_i exp(ε e_a), …)` the body-frame wrench on body `i` (torque,
force), by autodiff of `V` as for one body (`AbstractLieSystem.force`). A kick integrator
(`lievi.DEP`, `lievi.LiePoissonSplitting`, `lievi.MoserVeselov`, their `Composition`)
steps them as kick (all bodies) – free step of each body – kick (all bodies): the free step
of the product is the product of the free steps, so it is each body's own step, run on the
N bodies at once (`free_flow`: on SE(3), the structure-of-arrays kernel of
`lievi/_kernels/_se3.py` with the N bodies as its batch, or `jax.vmap` of the method's
step of one body). The coupling is evaluated once per step: the loop carries the end kick's force
to the next step's first kick (`AbstractKickIntegrator.step_cache`).

Symmetry: a potential of the relative poses, `V(h g_1, …, h g_N) = V(g_1, …, g_N)` for
every `h ∈ SE(3)`, leaves the Lagrangian invariant under the diagonal action of SE(3);
its momentum map is the total spatial momentum `Σ_i Ad*_{g_i⁻¹} m_i`, i.e. the total
linear momentum `Σ R_i P_i` and angular momentum about the world origin
`Σ (R_i Π_i + p_i × R_i P_i)` (`lievi.diagnostics.total_momentum`). The discrete flow
conserves it exactly (discrete Noether theorem, paper §2): the free steps conserve each
body's spatial momentum, and the kicks add wrenches whose spatial sum is zero.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, Scalar

from .._checks import check_real_dtype
from .._groups._base import MatrixLieGroup
from .._groups._se3 import SE3
from .._results import StepInfo
from ._base import AbstractLieSystem
from ._bodies import check_per_body_inertia, each_body, inertia_conditions, worst_body_report
from ._potential import AbstractPotential, as_potential
from ._rigid_body import RigidBody
from ._se3_body import RigidBodySE3, rigid_body_tensor, spd_solve
from ._side import Side


class RigidBodies(AbstractLieSystem):
    """N rigid bodies in space coupled by a potential: a left-invariant system on SE(3)ᴺ.

    **Arguments:**

    - `inertia`: principal moments `(N, 3)` or tensors `(N, 3, 3)` about each body's
      centre of mass, body frame.
    - `mass`: the masses, shape `(N,)`, each `> 0`.
    - `potential`: `None` (N free bodies), a `lievi.AbstractPotential` of the poses
      `g` of shape `(N, 4, 4)` (`lievi.SitePotential`, `lievi.SiteSprings`,
      `lievi.MutualGravity`), or any callable `V(g) -> scalar`.

    The state is `g` `(N, 4, 4)` (each body's origin at its centre of mass) and `m`
    `(N, 6)`, each row `(Π_i, P_i)` in body `i`'s frame, as for `lievi.RigidBodySE3`;
    `simulate`, `simulate_batch` and the diagnostics take them as they take one body's.
    `lievi.diagnostics.total_momentum` gives the total linear and angular momentum,
    `lievi.diagnostics.energy` the kinetic plus the coupling energy. With `N = 1` the
    runs equal those of `RigidBodySE3(inertia[0], mass[0], potential=…)`.
    """

    inertia: Float[Array, "N 3"] | Float[Array, "N 3 3"]
    mass: Float[Array, " N"]
    potential: AbstractPotential | None
    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)

    def __init__(self, inertia, mass, potential=None):
        check_real_dtype("inertia", inertia)
        check_real_dtype("mass", mass)
        inertia = jnp.asarray(inertia)
        check_per_body_inertia(inertia)
        mass = jnp.asarray(mass)
        if mass.shape != inertia.shape[:1]:
            raise ValueError(
                f"`mass` must have shape (N,) with N = {inertia.shape[0]} bodies (the leading "
                f"axis of `inertia`), got shape {mass.shape}."
            )
        self.inertia = inertia
        self.mass = mass
        self.potential = as_potential(potential)
        self.group = SE3
        self.side = Side.LEFT

    @property
    def n_bodies(self) -> int:
        return jnp.shape(self.mass)[-1]

    def element_shape(self):
        return (self.n_bodies, 4, 4)

    def momentum_shape(self):
        return (self.n_bodies, 6)

    def parameter_conditions(self):
        """Finite, each inertia symmetric positive definite and not singular to rounding
        (`inertia_conditions`), each mass `> 0`."""
        return (
            super().parameter_conditions()
            + inertia_conditions("inertia", self.tensor[..., :3, :3])
            + [(jnp.all(jnp.asarray(self.mass) > 0), "`mass` must be > 0 for every body.")]
        )

    @property
    def tensor(self) -> Float[Array, "N 6 6"]:
        """The kinetic tensors `diag(J_i, m_i 1)`, one per body (`(…, N, 6, 6)`, any leading
        axes of a batch of systems built with `jax.vmap` kept)."""
        mass = jnp.asarray(self.mass)
        inertia = jnp.asarray(self.inertia)
        per_body = inertia.shape[mass.ndim :]
        flat = jax.vmap(rigid_body_tensor)(inertia.reshape(-1, *per_body), mass.reshape(-1))
        return flat.reshape(*mass.shape, 6, 6)

    def force(self, g: Float[Array, "N 4 4"]) -> Float[Array, "N 6"]:
        """Each body's wrench `M_i = −d/dε V(…, g_i exp(ε e_a), …)`: `bodies_force`."""
        return bodies_force(self, g)

    def free_flow(self, integrator, g, m, h: Scalar):
        """Each body's free step by `integrator`, the N bodies at once: a body in vacuum
        (origin at its centre of mass) takes the method's own free body step where it has
        one (`AbstractKickIntegrator.free_body_step`), else its `free_step` of the body as
        a `RigidBodySE3`; where that is the step of the method's kernel for the free body
        on SE(3), the kernel's step with the N bodies as its batch
        (`AbstractBatchKernel.bodies_step`: the same code, traced once, not under
        `jax.vmap`). The step's report is that of the worst body: the first failing body's
        code, the most Newton iterations, the largest residual."""
        tensors = self.tensor
        kernel = integrator.free_kernel(RigidBodySE3(tensor=tensors[0]))
        if kernel is not None:
            g_next, m_next, result, iterations, residual = kernel.bodies_step(tensors, g, m, h)
            return g_next, m_next, worst_body_report(StepInfo(result, iterations, residual))

        def one(index, inertia, mass, g, m):
            body = integrator.body(index)  # with its per-run data of this body, if any
            own = body.free_body_step(inertia, mass, g, m, h)
            return body.free_step(RigidBodySE3(inertia, mass), g, m, h) if own is None else own

        return each_body(one, jnp.arange(self.n_bodies), self.inertia, self.mass, g, m)

    def principal_frames(self):
        """Each body's `RigidBody.principal_frames`, the body axis leading: computed once
        per run by a method that steps in the principal frame
        (`lievi.LiePoissonSplitting`)."""
        return jax.vmap(lambda J: RigidBody(J).principal_frames())(jnp.asarray(self.inertia))

    def free_discrete_lagrangian(self, integrator, g0, g1, h: Scalar) -> Scalar:
        """`Σ_i L_d^i(g0_i, g1_i)`: each body's discrete Lagrangian in vacuum, the discrete
        Lagrangian of the step `free_flow` takes on the body
        (`AbstractVariationalIntegrator.body_discrete_lagrangian`, else the method's
        `kinetic_discrete_lagrangian` of the body as a `RigidBodySE3`)."""

        def one(inertia, mass, a, b):
            own = integrator.body_discrete_lagrangian(inertia, mass, a, b, h)
            body = RigidBodySE3(inertia, mass)
            return integrator.kinetic_discrete_lagrangian(body, a, b, h) if own is None else own

        return jnp.sum(jax.vmap(one)(self.inertia, self.mass, g0, g1))

    def lagrangian(self, xi: Float[Array, "N 6"]) -> Scalar:
        return jnp.sum(xi * self.legendre(xi)) / 2

    def legendre(self, xi: Float[Array, "N 6"]) -> Float[Array, "N 6"]:
        return jnp.einsum("nij,nj->ni", self.tensor, xi)

    def velocity(self, m: Float[Array, "N 6"]) -> Float[Array, "N 6"]:
        tensor = self.tensor.astype(jnp.result_type(self.tensor, m))
        return jax.vmap(spd_solve)(tensor, m)

    def velocity_size(self, m: Float[Array, "N 6"]) -> Float[Array, " N"]:
        """Each body's rotation rate `|J_i⁻¹Π_i|` (`SE3.exp_norm` of its velocity), from the
        3×3 inertia alone: the 6×6 solve of `velocity`, at every step's check, was a sixth
        of the instructions of a splitting run's program (its compile time ~1 s more)."""
        inertia = jnp.asarray(self.inertia).astype(jnp.result_type(self.inertia, m))
        Pi = m[..., :3]
        omega = Pi / inertia if inertia.ndim == Pi.ndim else jax.vmap(spd_solve)(inertia, Pi)
        return jnp.linalg.norm(omega, axis=-1)

    def energy(self, m: Float[Array, "N 6"]) -> Scalar:
        """The kinetic energy `Σ_i ½ m_iᵀ M_i⁻¹ m_i` (`lievi.diagnostics.energy` adds `V`)."""
        return jnp.sum(m * self.velocity(m)) / 2


def bodies_force(system: AbstractLieSystem, g: Float[Array, "N 4 4"]) -> Float[Array, "N 6"]:
    """The wrenches `M_i = −d/dε V(…, g_i exp(ε e_a), …)` of a system of N bodies on
    SE(3)ᴺ: in closed form where its potential gives them
    (`AbstractPotential.value_and_body_wrenches`, e.g. the site forces of
    `lievi.SitePotential`, uniform gravity on jointed bodies), else by autodiff
    (`AbstractLieSystem.force`). NaN where `V(g)` is not finite, either way."""
    potential = system.potential
    closed = None if potential is None else potential.value_and_body_wrenches(g)
    if closed is None:
        return AbstractLieSystem.force(system, g)
    value, wrench = closed
    wrench = wrench.astype(jnp.result_type(g, float))
    return jnp.where(jnp.isfinite(value), wrench, jnp.nan)
