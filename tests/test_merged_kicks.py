"""The composition's kick kernel merges adjacent half kicks (`KickKernel.step_stages`):
the same map as the stages run one after the other, and the composition's order.

The kernel is run directly (its batched structure-of-arrays step, jitted with a traced
step `h`), so each variant compiles once.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np

import lievi
from lievi._kernels._base import AbstractBatchKernel

# Merged against unmerged kicks, relative to the momentum scale (float64): one addition
# fewer per merge, over 40 steps of 3 stages.
MERGED = 1e-13
INERTIA = jnp.array([2.0, 1.0, 2 / 3])
COM = jnp.array([0.1, 0.05, 0.4])


def _top():
    return lievi.heavy_top(INERTIA, 1.0, COM, gravity=1.0)


def _initial(batch=4):
    angles = jnp.linspace(0.2, 1.1, batch)
    g0 = jax.vmap(lambda a: lievi.SO3.exp(jnp.array([a, 0.3, -0.2])))(angles)
    m0 = jnp.stack([jnp.cos(angles), 0.3 * angles, jnp.sin(angles)], axis=-1)
    return g0, m0


@functools.cache
def _runner(merged: bool):
    """`(Γ_N, Π_N)` of the order-4 composition of the splitting's kick kernel after `n` steps
    `h`, its stages run by the kick kernel's own loop (`merged`) or by the default loop of
    `AbstractBatchKernel` (the stages one after the other, two half kicks each)."""
    kernel = _kernel()
    inner = kernel.inner
    loop = type(inner) if merged else AbstractBatchKernel

    @jax.jit
    def step(g, m, h):
        constants = inner.constants(kernel.physics(_top()))
        params = loop.prepare_stages(inner, constants, h, kernel.coefficients)
        return loop.step_stages(inner, params, g, m, True)[:2]

    def run(g0, m0, h, n):
        g, m = inner.carried(g0), tuple(m0[:, i] for i in range(3))
        for _ in range(n):
            g, m = step(g, m, h)
        return jnp.stack(g), jnp.stack(m)

    return run


def _kernel():
    # On the reduced state `(Π, Γ)` (3 arrays carried, not 9): a smaller program to compile,
    # the same kicks.
    integrator = lievi.Composition(lievi.LiePoissonSplitting(), 4)
    kernel = integrator.batch_kernel(_top()).reduced()
    assert type(kernel.inner).__name__ == "KickKernel"
    return kernel


def test_merged_kicks_equal_the_unmerged_stages():
    g0, m0 = _initial()
    args = (g0, m0, jnp.asarray(0.1), 40)
    g, m = _runner(True)(*args)
    g_ref, m_ref = _runner(False)(*args)
    scale = float(jnp.max(jnp.abs(m_ref)))
    np.testing.assert_allclose(m, m_ref, rtol=0, atol=MERGED * scale)
    np.testing.assert_allclose(g, g_ref, rtol=0, atol=MERGED)
    # Two different loops were compared (the kick kernel has its own).
    assert type(_kernel().inner).step_stages is not AbstractBatchKernel.step_stages


def test_merged_kicks_keep_the_order():
    """The order-4 composition of the splitting on the heavy top, with merged kicks, has
    observed order 4 at T = 2: the differences of the final states at `n`, `2n`, `4n` steps
    shrink by `2⁴` (to ±0.2 in the exponent)."""
    T, steps = 2.0, (8, 16, 32)
    g0, m0 = _initial()
    run = _runner(True)
    finals = [
        np.concatenate([np.ravel(x) for x in run(g0, m0, jnp.asarray(T / n), n)]) for n in steps
    ]
    d1, d2 = (np.max(np.abs(a - b)) for a, b in zip(finals, finals[1:]))
    assert abs(np.log2(d1 / d2) - 4) <= 0.2, (d1, d2)
