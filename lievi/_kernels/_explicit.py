"""Fast batched steps of the explicit rigid-body integrators on SO(3): splitting and RK4.

The structure-of-arrays counterparts of `LiePoissonSplitting` (`_splitting.py`, paper §6)
and `RK4` (`_rk4.py`) for a rigid body with principal moments `I`, as `_kernels/_so3.py` is
for `DEP`: every component its own `(B,)` array (batch minor), closed forms, no batched
3×3 matrix products. They compute the same iterates as the per-body methods to round-off
(the tests compare them).
"""

from __future__ import annotations

import jax.numpy as jnp

from .._results import RESULTS
from . import _explicit_adjoints
from ._base import AbstractBatchKernel, per_run


def finite_result(m, g):
    finite = jnp.isfinite(m[0])
    for x in (*m[1:], *g):
        finite = finite & jnp.isfinite(x)
    return jnp.where(finite, RESULTS.successful, RESULTS.nonfinite).astype(jnp.int32)


def splitting_step(g, m, rate):
    """One `LiePoissonSplitting` step: axes 0, 1 (h/2), 2 (h), 1, 0 (h/2), as `_splitting.py`.

    Sub-flow about axis `p` for a fraction `f` of the step: `F_j = exp(α ê_p)` with
    `α = f Π_p h/I_p`, `Π ← F_jᵀ Π` (`Π_p` does not change). The five rotations are
    composed as unit quaternions `(cos α/2, sin α/2 e_p)` into `F = F_1⋯F_5`, and
    `g ← g F` once (equal to rotating `g` five times, to round-off). `g`: 9 arrays
    (row-major), or only some of its rows (as `dep_step`), `m`: 3 arrays, `rate`: `h/I_p`,
    3 arrays or scalars. Returns `(g_next, Pi_next, result)`. Differentiable by the
    hand-written tangent of `_explicit_adjoints.splitting_flow`.

    Cost (XLA on CPU, float64): the step is bound by the arrays of `B` numbers it writes
    and reads back, more than by its arithmetic. Per body-step the five sine/cosine
    pairs of the half angles (10 numbers, each from one polynomial) and the four
    quaternion components are stored; the momenta between sub-flows and `F` are
    recomputed where they are read. Storing the 9 entries of `F` instead of the
    quaternion, and each angle (a division by `I/h`), was measured 1.2–1.4× slower at
    batch 1e5 (same run).
    """
    g, m = _explicit_adjoints.splitting_flow(tuple(g), tuple(m), tuple(rate))
    return g, m, finite_result(m, g)


def rk4_step(g, m, rate):
    """One `RK4` step on `ṁ = Π × Ω`, `ġ = g Ω̂`, `Ω = I⁻¹Π` (`_rk4.py`), component-wise.

    `rate`: `h/I_p`, 3 arrays or scalars. The step and the moments enter only through
    these ratios (`h f(y; I) = f(y; I/h)`, the field is linear in `I⁻¹`): the stages use
    the increments `h k_i = (g ŵ_i, Π_i × w_i)`, `w_i = (h/I)·Π_i`, so reverse mode
    carries three cotangents of the parameters, not four. Differentiable by the
    hand-written tangent of `_explicit_adjoints.rk4_flow`.
    """
    g_next, m_next = _explicit_adjoints.rk4_flow(tuple(g), tuple(m), tuple(rate))
    return g_next, m_next, finite_result(m_next, g_next)


def explicit_info(m):
    # Explicit: no Newton iterations, zero residual (as the per-body `StepInfo`).
    return jnp.zeros(jnp.shape(m[0]), jnp.int32), jnp.zeros(jnp.shape(m[0]), m[0].dtype)


class SplittingKernel(AbstractBatchKernel):
    """`splitting_step` for `LiePoissonSplitting`."""

    def prepare(self, inertia, h):
        return per_run([h / moment for moment in inertia])

    def step(self, params, g, m, alive):
        g_next, m_next, result = splitting_step(g, m, params)
        return (g_next, m_next, result, *explicit_info(m))


class RK4Kernel(AbstractBatchKernel):
    """`rk4_step` for `RK4`."""

    def prepare(self, inertia, h):
        return per_run([h / moment for moment in inertia])

    def step(self, params, g, m, alive):
        g_next, m_next, result = rk4_step(g, m, params)
        return (g_next, m_next, result, *explicit_info(m))
