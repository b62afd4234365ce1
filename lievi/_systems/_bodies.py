"""What the systems of several rigid bodies share (`lievi.RigidBodies` on SE(3)ᴺ,
`lievi.RigidRotors` on SO(3)ᴺ): the shape check of their per-body inertias and the free
step of a product group taken body by body.

On a product group `Gᴺ` with a block-diagonal kinetic energy the free flow is the
product of the bodies' free flows, and so is the free step of every kick integrator
(its discrete Lagrangian is the sum of the bodies', paper §2 and (3.3)): the N free steps
run at once as one `jax.vmap` of the method's step of one body (`each_body`), or, where
the method has a kernel for the body, as that kernel's step with the N bodies as its
batch (`AbstractKickIntegrator.free_bodies_step`). The step's report is that of the
worst body.
"""

from __future__ import annotations

import jax
import jax.numpy as jnp

from .._groups._so3 import SO3
from .._results import RESULTS


def check_per_body_inertia(inertia) -> None:
    """Raise `ValueError` unless `inertia` is `(N, 3)` principal moments or `(N, 3, 3)`
    tensors, one per body, with `N ≥ 1`."""
    shape = jnp.shape(inertia)
    if (len(shape) == 2 and shape[-1] == 3) or (len(shape) == 3 and shape[-2:] == (3, 3)):
        if shape[0] >= 1:
            return
        raise ValueError("`inertia` describes no body: pass at least one row.")
    raise ValueError(
        "`inertia` must be principal moments of shape (N, 3) or tensors of shape (N, 3, 3), "
        f"one per body, got shape {shape}."
    )


def worst_body_report(info):
    """One report for a step of N bodies from the N bodies' reports (a `StepInfo` whose
    fields have a leading body axis): the first failing body's code, the most Newton
    iterations, the largest residual."""
    failed = info.result != RESULTS.successful
    result = jnp.where(jnp.any(failed), info.result[jnp.argmax(failed)], RESULTS.successful)
    return type(info)(result.astype(jnp.int32), jnp.max(info.iterations), jnp.max(info.residual))


def each_body(step, *per_body):
    """`step(*args_i) -> (g_i, m_i, StepInfo)` on every body at once (`jax.vmap` over the
    leading body axis of each of `per_body`), with the report of the worst body."""
    g_next, m_next, info = jax.vmap(step)(*per_body)
    return g_next, m_next, worst_body_report(info)


def orthonormal_frame(R, *spatial):
    """`(R', v_1, …)`: the rotation `R` moved back onto SO(3) (`SO3.project`, its
    orthogonality defect `δ` made `O(δ²)`), and the body-frame vectors `v_a = R'ᵀ s_a` of
    the spatial vectors `s_a` (`(3,)` each) in that frame.

    The kicks of a coupling of the relative rotations conserve the total spatial angular
    momentum only for orthogonal rotations (their torques' spatial sum vanishes on the
    group), so each body's rotation is kept orthogonal to an ulp after its free step, as
    `SE3.compose` keeps a pose's. The body momenta are then read off the spatial ones,
    which the free step conserves, with the projected rotation: with the rotation before
    the projection its rounding defect — of one sign step after step for a steady spin,
    or through a principal-axis change of frame (`cos² + sin² − 1` rounds alike) — would
    move the spatial momentum by a few ulps per step, in one direction (measured: 7e-11
    of the total angular momentum of a binary after 1e5 steps)."""
    R = SO3.project(R)
    return (R, *(R.T @ s for s in spatial))
