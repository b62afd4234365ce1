"""The Moser–Veselov discretization of the (generalized) rigid body (paper §5, (5.4)–(5.6)).

For the left-invariant generalized rigid body on SO(n) with inertia operator
`J(ξ) = Λξ + ξΛ`, the Moser–Veselov step from `(g_k, Π_k)` is (docs/theory/conventions.md)

    Ωᵀ Λ − Λ Ω = h Π̂_k,   Ω ∈ SO(n)          (the second line of (5.6); DEP (5.4)),
    Π̂_{k+1} = Ω Π̂_k Ωᵀ                         (the first line of (5.6); DLP (5.5)),
    g_{k+1} = g_k Ωᵀ                             (reconstruction, (5.7₁)).

The increment is `F = Ωᵀ = g_k⁻¹ g_{k+1}` (the paper's `f_{k+1,k} = Ω`). The discrete
Lagrangian is Moser–Veselov's, `L_d(g_k, g_{k+1}) = tr((I − g_kᵀ g_{k+1}) Λ)/h`
(the paper's `−tr(g_k Λ g_{k+1}ᵀ)/h²` scaled by `h` and shifted by a constant, so that
`L_d ≈ h·l(ξ)` as for `DEP` and its discrete Legendre transform gives `Π` itself).

Solving the implicit equation. Write `F = cay(X) = (I − X/2)⁻¹(I + X/2)`, `X ∈ so(n)`
(the Cayley chart of Lewis–Simo (5.7), which covers every rotation with no angle equal
to π — every increment a sensible step can produce). Multiplying `F Λ − Λ Fᵀ = h Π̂` by
`(I − X/2)` on the left and `(I + X/2)` on the right, and using that `X` commutes with
`cay(X)`, turns the equation into the *quadratic* equation

    J(X) = Λ X + X Λ = h (I − X/2) Π̂ (I + X/2),

exactly equivalent to the original. Its right-hand side is `h·dcayinv(x) Π` in
coordinates, and its left-hand side is the Legendre map of the system, `I x` on SO(3). We
solve it by Newton's method from the explicit-Euler guess `h I⁻¹ Π` (O(h²) from the root;
the Jacobian there is `J + O(h)`, well conditioned since `J` is positive definite) with
`lievi._newton.newton_solve`, so the step differentiates by the implicit function theorem.

The rigid body on SO(3) maps to `Λ = ½ tr(I)·Id − I` (for principal moments
`I₁ = Λ₂ + Λ₃, …`). A full inertia tensor gives a symmetric, non-diagonal `Λ`; the
equations above hold verbatim for any symmetric `Λ` (`Λx̂ + x̂Λ = hat((tr Λ − Λ)x)`), and
they are equivariant under conjugation by a rotation, so the step equals the diagonal
step in the principal frame (the tests check this) without an eigendecomposition —
which keeps derivatives with respect to the inertia finite for degenerate moments.
Moments that violate the triangle inequality (`I₃ ≥ I₁ + I₂`, not a physical body) give
some `Λᵢ ≤ 0`; only the pair sums `Λᵢ + Λⱼ = I_k > 0` enter `J`, so the scheme is still
well defined and is used unchanged.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import as_int, check_shape, is_concrete
from .._kernels._so3 import NewtonKernel
from .._kernels._so3_equations import MoserVeselovEquation
from .._newton import check_newton_options, newton_solve, newton_tolerance
from .._results import RESULTS
from .._systems._base import AbstractLieSystem
from ._base import AbstractVariationalIntegrator, StepInfo
from ._drift import rotation_and_drift, rotation_and_drift_lagrangian


def check_rigid_body(method: str, system: AbstractLieSystem) -> None:
    """Raise `ValueError` unless `system` is a rigid body the method supports: one with
    an inertia operator `J(ξ̂) = Λξ̂ + ξ̂Λ` (`AbstractLieSystem.lambda_matrix`)."""
    if system.lambda_matrix() is None:
        raise ValueError(
            f"{method} integrates the free rigid body only: pass a `lievi.RigidBody` or a "
            f"`lievi.GeneralizedRigidBody`, got {type(system).__name__}. For any other "
            "reduced Lagrangian use `lievi.DEP`."
        )
    if system.side != "left":
        raise ValueError(f"{method}: the rigid body must be left-invariant (side='left').")


def check_pair_sums(method: str, system: AbstractLieSystem) -> None:
    """Eagerly reject `Λᵢ + Λⱼ ≤ 0` for some plane (`principal_planes`), where the system's
    parameters are concrete: a system built around its own checks (e.g. by `tree_at`).
    A traced system is left to its `parameter_conditions` in the run, and returns before
    any arithmetic: under `ensure_compile_time_eval` the index arithmetic of a traced
    tensor's principal frame still ran eagerly, two small programs per eager run."""
    if not is_concrete(*jax.tree.leaves(eqx.filter(system, eqx.is_array))):
        return
    with jax.ensure_compile_time_eval():
        # Evaluated now even inside a trace that closed over a concrete system.
        moments = system.principal_planes()[0]
    if not is_concrete(moments):
        return
    moments = np.asarray(moments, float)
    if np.any(moments <= 0):
        raise ValueError(
            f"{method}: the inertia operator must be positive definite, Λᵢ + Λⱼ > 0 for "
            f"every plane; got plane moments {moments} (for a `RigidBody`, the principal "
            "moments)."
        )


class MoserVeselov(AbstractVariationalIntegrator):
    """The Moser–Veselov integrator for the free rigid body (paper §5, Theorem 5.1).

    Second order, symplectic on `SO(n) × SO(n)`, Lie–Poisson on `so(n)*` (Casimirs kept to
    round-off), conserves the spatial momentum; implicit, solved by Newton's method on the
    Cayley chart (see the module docstring). Equivalent to the DEP algorithm (5.4) with the
    discrete Lagrangian `tr((I − g_kᵀg_{k+1})Λ)/h` and to the Lewis–Simo algorithm (5.7).

    Works for `RigidBody` (principal moments or a full tensor) and `GeneralizedRigidBody`
    on SO(n), n ≥ 3.

    **Arguments:**

    - `rtol`, `atol`: the Newton solve stops when the residual of `J(X)/h − (I − X/2)Π̂(I + X/2)`
      (momentum units) satisfies `‖r‖_∞ ≤ atol + rtol·‖Π‖_∞`. Default: `rtol` = 64 ulps of
      the dtype, `atol` = 0 (a relative test: the step does not depend on the units).
    - `max_steps`: maximum Newton iterations per step; exceeding it is reported as
      `RESULTS.newton_not_converged`.
    """

    rtol: float | None = eqx.field(default=None, static=True)
    atol: float | None = eqx.field(default=None, static=True)
    max_steps: int = eqx.field(default=20, static=True, converter=as_int)

    def __check_init__(self):
        check_newton_options(self.max_steps, self.rtol, self.atol)

    def order(self) -> int:
        return 2

    def is_symmetric(self) -> bool:
        # −L_d(g₁, g₀; −h) = tr((I − g₁ᵀg₀)Λ)/h = L_d(g₀, g₁; h): tr(AᵀΛ) = tr(AΛ).
        return True

    def free_body_step(self, inertia, mass, g, m, h: Scalar):
        # A method of the rotation: the body's rotation by it, its translation exactly.
        return rotation_and_drift(self, inertia, mass, g, m, h)

    def body_discrete_lagrangian(self, inertia, mass, g0, g1, h: Scalar):
        # The discrete Lagrangian of `free_body_step`: the rotation's, the exact drift's.
        return rotation_and_drift_lagrangian(self, inertia, mass, g0, g1, h)

    def own_step(self) -> bool:
        # The kernels and the step cache compute this class's own step (not a subclass's).
        return type(self) is MoserVeselov

    def kernels(self):
        return (NewtonKernel(MoserVeselovEquation(), self.rtol, self.atol, self.max_steps),)

    def kinetic_discrete_lagrangian(self, system: AbstractLieSystem, g0, g1, h: Scalar) -> Scalar:
        """`tr((I − g₀ᵀg₁)Λ)/h`, Moser–Veselov's `tr(g_k Λ g_{k+1}ᵀ)` up to scale and shift."""
        check_rigid_body("MoserVeselov", system)
        Lambda = system.lambda_matrix()
        increment = system.group.inverse(g0) @ g1
        eye = jnp.eye(increment.shape[-1], dtype=increment.dtype)
        return jnp.trace((eye - increment) @ Lambda) / h

    @staticmethod
    def residual(system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar):
        """`x ↦ J(x)/h − vee((I − X/2) Π̂ (I + X/2))`, in momentum units like DEP's."""
        group = system.group
        M = group.hat(m)
        eye = jnp.eye(group.matrix_dim, dtype=m.dtype)

        def residual(x):
            X = group.hat(x)
            return system.legendre(x) / h - group.vee((eye - X / 2) @ M @ (eye + X / 2))

        return residual

    def on_branch(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar, x):
        """The branch rule: `x` is the root continued from `h → 0` — certified by the
        symmetric part of the residual's Jacobian (times `sign h`) being positive definite
        at `x`.

        The residual is quadratic in `x`, so its Jacobian is affine and the set where its
        symmetric part is positive definite is convex; on a convex set a map with a
        positive definite symmetric Jacobian is injective. So there is at most one root
        there, and for small `h` (Jacobian ≈ `J/h`) it is the root near `h I⁻¹Π`. A root
        outside that set (another root of the quadratic, or the branch past its fold) is
        reported as `RESULTS.step_too_large`, on both the generic and the batched path.
        """
        # Times sign(h): a negative step (an inner stage of `Composition`) has J ≈ J/h < 0.
        jacobian = jax.jacfwd(self.residual(system, m, h))(x) * jnp.sign(h)
        symmetric = (jacobian + jacobian.T) / 2
        return jnp.all(jnp.isfinite(jnp.linalg.cholesky(symmetric)))

    def solve_increment(self, system: AbstractLieSystem, m: Float[Array, " d"], h: Scalar):
        """Solve `J(X) = h (I − X/2) Π̂ (I + X/2)` for the Cayley coordinates `x` of `F = Ωᵀ`."""
        residual = self.residual(system, m, h)
        tolerance = newton_tolerance(jnp.max(jnp.abs(m)), m.dtype, self.rtol, self.atol)
        return newton_solve(residual, h * system.velocity(m), tolerance, self.max_steps)

    def free_step(self, system: AbstractLieSystem, g, m, h: Scalar):
        check_rigid_body("MoserVeselov", system)
        check_pair_sums("MoserVeselov", system)
        group = system.group
        n, d = group.matrix_dim, group.algebra_dim
        check_shape("g", g, (n, n), f"an element of SO({n})")
        check_shape("m", m, (d,), f"momentum coordinates of so({n})*")
        # The kernel (the rigid body with principal moments) and the generic solve end on
        # the same root or report the same failure: one branch rule (`on_branch`).
        fast = self.kernel_step(system, g, m, h)
        if fast is not None:
            return fast
        x, info = self.solve_increment(system, m, h)
        F = group.cay(x)  # F = Ωᵀ = g_k⁻¹ g_{k+1}
        g_next = g @ F
        # Π̂_{k+1} = Ω Π̂_k Ωᵀ = Fᵀ Π̂_k F: a conjugation, so Casimirs are kept to round-off
        # whatever the Newton residual.
        m_next = group.vee(F.T @ group.hat(m) @ F)
        result = jnp.where(info.converged, RESULTS.successful, RESULTS.newton_not_converged)
        # One branch rule on every path (see `on_branch`): a root off it is a failure.
        off_branch = info.converged & ~self.on_branch(system, m, h, x)
        result = jnp.where(off_branch, RESULTS.step_too_large, result)
        finite = jnp.isfinite(info.residual) & jnp.all(jnp.isfinite(m_next))
        result = jnp.where(finite, result, RESULTS.nonfinite)
        return g_next, m_next, StepInfo(result, info.iterations, info.residual)
