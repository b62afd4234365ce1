"""The exact free flow of an axisymmetric rigid body, as structure of arrays.

The kernel of `lievi.SymmetricTopSplitting`'s free flow (`_integrators/_symmetric_top.py`)
for principal moments `(I₁, I₁, I₃)`: `F = exp(tΠ/I₁) exp(t c Π₃ e₃)`, `c = 1/I₃ − 1/I₁`,
`g ← g F`, `Π ← Fᵀ Π`. Each factor is a unit quaternion — `(cos φ, sin φ Π/|Π|)` with
`φ = t|Π|/(2I₁)`, and `(cos ψ, 0, 0, sin ψ)` with `ψ = t c Π₃/2` — their product one sparse
quaternion product, and `F` is rebuilt from it as the axis splitting's (`_explicit_primal`):
two sine–cosine pairs and a square root a step, where the axis splitting takes five pairs.
"""

from __future__ import annotations

import jax.numpy as jnp

from .._results import RESULTS
from ._base import AbstractBatchKernel, materialise, ones
from ._explicit import explicit_info, finite_result
from ._explicit_primal import (
    matmul3,
    quaternion_product,
    rotation_minus_identity,
    sincos,
)
from ._soa import times_increment


def axisymmetric_flow(g, m, rate, spin_rate):
    """`(g F, Fᵀ Π)` for `rate = t/I₁`, `spin_rate = t(1/I₃ − 1/I₁)` (scalars or arrays).

    `sin φ / |Π|` is `(rate/2)·sin φ/φ`; at `Π = 0` (no turn) it is taken as `rate/2`, and
    the square root sees 1 there, so the derivative stays finite."""
    one = ones(m[0])
    squared = m[0] * m[0] + m[1] * m[1] + m[2] * m[2]
    still = squared == 0
    size = jnp.sqrt(jnp.where(still, 1, squared))
    half = 0.5 * rate
    # The two sine–cosine pairs and the product stored once each (`materialise`): left to
    # XLA's fusion, each consumer recomputed them (measured, Lagrange top, batch 256, one
    # core: 25 ns a body-stage of the order-6 step stored so, 28 with the product alone
    # stored, 57 with nothing stored; the axis splitting's composition 40).
    sin_phi, cos_phi, sin_psi, cos_psi = materialise(
        (*sincos(half * size), *sincos((0.5 * spin_rate) * m[2])), one
    )
    scale = jnp.where(still, half, sin_phi / size)
    turn = (cos_phi, scale * m[0], scale * m[1], scale * m[2])
    spin = (cos_psi, 0.0, 0.0, sin_psi)
    quaternion = materialise(quaternion_product(turn, spin), one)
    D = rotation_minus_identity(quaternion)
    F = tuple(d + 1 if i % 4 == 0 else d for i, d in enumerate(D))
    return times_increment(g, D), matmul3(tuple(m), F)


def mean_first_moments(inertia):
    """`I₁ = (I_1 + I_2)/2` of principal moments (equal for a symmetric body): the method's
    model of the body, symmetric in the two moments it takes as equal."""
    return 0.5 * (inertia[0] + inertia[1])


def is_axisymmetric(I_1, I_2, I_3):
    """Principal moments with `I_1 = I_2` to a few ulps of their size, elementwise: the one
    rule of both checks — eager on concrete moments (`check_axisymmetric`, a `ValueError`)
    and traced in the run, where a body that fails it ends as `RESULTS.invalid_input`, not
    as the flow of another body. Operators only, so NumPy and JAX arrays alike."""
    eps = jnp.finfo(I_1.dtype).eps
    return abs(I_1 - I_2) <= 8 * eps * (abs(I_1) + abs(I_2) + abs(I_3))


def axisymmetric_result(result, axisymmetric):
    """`result`, or `invalid_input` where the body is not axisymmetric (`is_axisymmetric`)."""
    return jnp.where(axisymmetric, result, RESULTS.invalid_input).astype(jnp.int32)


class AxisymmetricKernel(AbstractBatchKernel):
    """`axisymmetric_flow` for `lievi.SymmetricTopSplitting`."""

    def prepare(self, inertia, h):
        I1 = mean_first_moments(inertia)
        return h / I1, h * (1 / inertia[2] - 1 / I1), is_axisymmetric(*inertia)

    def step(self, params, g, m, alive):
        rate, spin_rate, axisymmetric = params
        g_next, m_next = axisymmetric_flow(g, m, rate, spin_rate)
        result = axisymmetric_result(finite_result(m_next, g_next), axisymmetric)
        return (g_next, m_next, result, *explicit_info(m))
