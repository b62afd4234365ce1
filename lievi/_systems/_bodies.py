"""What the systems of several rigid bodies share (`lievi.RigidBodies` on SE(3)ᴺ,
`lievi.RigidRotors` on SO(3)ᴺ): the checks of their per-body inertias (shared with
`lievi.RigidBodySE3`) and the free step of a product group taken body by body.

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

from .._checks import Conditions, shown, spd_conditions
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


# The bound on `det J / (tr J)³` below which an inertia `J` is taken as singular: rounding
# alone leaves a singular tensor (a dumbbell's, summed from its point masses) a determinant
# of a few ulps of `(tr J)³`; a body whose smallest moment is `r` times its largest has a
# ratio of at least `r/54` (the moments obey the triangle inequality), so in float64 only
# bodies with `r ≲ 1e-13` are refused, in float32 `r ≲ 5e-5`.
_SINGULAR_ULPS = 8


def inertia_conditions(name: str, inertia) -> Conditions:
    """Inertia tensors `(…, 3, 3)` finite, symmetric, positive definite
    (`spd_conditions`) and not singular to rounding (`regular_inertia`), as conditions."""
    finite, symmetric, positive = spd_conditions(name, inertia)
    return [finite, symmetric, regular_inertia(name, inertia), positive]


def regular_inertia(name: str, inertia):
    """The condition that inertia tensors `(…, 3, 3)` are not singular to rounding:
    `det J > 8ε (tr J)³`. A body of point masses on one line (a dumbbell) fails it: its
    moment about that line is 0, or ±1e-16 of the others after rounding, which a test of
    positive definiteness can pass; its first step would then spin it about that line
    infinitely fast and fail as a step too large. The message names `extra_inertia`, the
    fix. Put before the test of positive definiteness, whose message has no hint."""
    j = jnp.asarray(inertia)
    j = j.astype(jnp.result_type(j, float))
    j = jnp.where(jnp.all(jnp.isfinite(j)), j, jnp.eye(3, dtype=j.dtype))
    trace = j[..., 0, 0] + j[..., 1, 1] + j[..., 2, 2]
    # The determinant by cofactors: elementwise, so a batch of any size runs where the
    # state runs (as `spd_conditions`' pivots).
    det = (
        j[..., 0, 0] * (j[..., 1, 1] * j[..., 2, 2] - j[..., 1, 2] * j[..., 2, 1])
        - j[..., 0, 1] * (j[..., 1, 0] * j[..., 2, 2] - j[..., 1, 2] * j[..., 2, 0])
        + j[..., 0, 2] * (j[..., 1, 0] * j[..., 2, 1] - j[..., 1, 1] * j[..., 2, 0])
    )
    regular = det > _SINGULAR_ULPS * jnp.finfo(j.dtype).eps * trace**3
    body = shown(jnp.argmin(regular), " (body {})") if j.ndim == 3 else ""
    return (
        jnp.all(regular),
        f"`{name}` is singular{body}, or singular up to rounding: the body has no moment "
        "about some axis, as a body of point masses on one line (a dumbbell) about that "
        "line, and would spin about it infinitely fast. Give it the moments of its extent: "
        "`extra_inertia=` of `lievi.gravitating_bodies` or `lievi.full_body_problem` (e.g. "
        "the inertia of a rod, or of the spheres at its ends), or a positive definite "
        f"`{name}`.",
    )


def worst_body_report(info):
    """One report for a step of N bodies from the N bodies' reports (a `StepInfo` whose
    fields have a leading body axis): the first failing body's code, the most Newton
    iterations, the largest residual."""
    # One reduction over the bodies of `index · codes + code` (a failed body's), the
    # smallest the first failure: XLA recomputes the elementwise work that produces the
    # codes (a free step's checks) in each reduction that reads it, and `any`, `argmax`
    # and the gather of that body's code were three copies (of a binary's 3157-operation
    # step program, 550 operations).
    codes = len(RESULTS.messages)
    bodies = info.result.shape[-1]
    failed = info.result != RESULTS.successful
    key = jnp.where(failed, jnp.arange(bodies) * codes + info.result, bodies * codes)
    first = jnp.min(key)
    result = jnp.where(first < bodies * codes, first % codes, RESULTS.successful)
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
