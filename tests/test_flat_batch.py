"""Under `jax.vmap`, a kernel's Newton solve runs once on the batch merged into its bodies
(`lievi._kernels._flat_batch.bodies_batched`): the same values as each body's own solve,
in values and in derivatives (forward and reverse mode) of `jax.vmap(simulate)`."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF
from lievi._kernels._flat_batch import bodies_batched


def newton_sqrt(traced):
    """A per-body solve as the kernels write it: elementwise, a `while_loop` while any body
    is above tolerance, converged bodies left alone. Records the shapes it is traced with."""

    def solve(a, x0, tolerance):
        traced.append(jnp.shape(a))

        def above(x):
            return jnp.abs(x * x - a) > tolerance * a

        def body(carry):
            x, iterations = carry
            step = above(x)
            return jnp.where(step, (x + a / x) / 2, x), iterations + step

        start = (jnp.broadcast_to(x0, jnp.shape(a)), jnp.zeros(jnp.shape(a), jnp.int32))
        return jax.lax.while_loop(lambda c: jnp.any(above(c[0])), body, start)

    return solve


def rows(solve, a, x0, tolerance):
    """`solve` on each body of each system alone, stacked: the reference."""
    out = [[solve(a[i, j], x0[j], tolerance) for j in range(a.shape[1])] for i in range(a.shape[0])]
    return tuple(jnp.array([[o[k] for o in row] for row in out]) for k in range(2))


@pytest.fixture
def values():
    rng = np.random.default_rng(0)
    return jnp.asarray(rng.uniform(0.5, 400.0, size=(4, 3))), jnp.asarray(rng.uniform(1, 2, 3))


def test_vmap_merges_the_batch_into_the_bodies(values):
    """A `(4, 3)` batch of 3-body solves is traced once for 12 bodies, not under a batched
    loop; each body takes its own iterations (many differ) to the same root."""
    a, x0 = values
    traced = []
    x, iterations = jax.vmap(bodies_batched(newton_sqrt(traced)), in_axes=(0, None, None))(
        a, x0, 1e-15
    )
    assert (12,) in traced  # without the rule: traced for (3,) only, the loop batched
    expected = rows(newton_sqrt([]), a, x0, 1e-15)
    np.testing.assert_allclose(x, expected[0], rtol=ROUNDOFF)
    np.testing.assert_array_equal(iterations, expected[1])
    assert len(set(np.asarray(iterations).ravel())) > 1
    np.testing.assert_allclose(x, jnp.sqrt(a), rtol=ROUNDOFF)


def test_batched_scalars_nested_vmap_and_one_body(values):
    """A batched shared scalar (the tolerance) is spread over the bodies; nested `vmap`s
    merge every axis; a batch of one-body (scalar) solves is traced for `(B,)` arrays."""
    a, x0 = values
    tolerances = jnp.array([1e-15, 1e-6])
    traced = []
    solve = bodies_batched(newton_sqrt(traced))
    x, iterations = jax.vmap(solve, in_axes=(None, None, 0))(a[0], x0, tolerances)
    assert (6,) in traced
    for k, tolerance in enumerate(tolerances):
        expected = rows(newton_sqrt([]), a[:1], x0, tolerance)
        np.testing.assert_array_equal(iterations[k], expected[1][0])
        np.testing.assert_allclose(x[k], expected[0][0], rtol=ROUNDOFF)

    nested = jax.vmap(jax.vmap(solve, in_axes=(0, None, None)), in_axes=(0, None, None))
    x, _ = nested(jnp.stack([a, 2 * a]), x0, 1e-15)
    assert (24,) in traced
    np.testing.assert_allclose(x, jnp.sqrt(jnp.stack([a, 2 * a])), rtol=ROUNDOFF)

    x, _ = jax.vmap(solve, in_axes=(0, None, None))(a[:, 0], x0[0], 1e-15)
    assert (4,) in traced
    np.testing.assert_allclose(x, jnp.sqrt(a[:, 0]), rtol=ROUNDOFF)


def se3_bodies(count):
    rng = np.random.default_rng(7)
    inertia = jnp.asarray(rng.uniform(0.5, 2.0, size=(count, 3)))
    mass = jnp.asarray(rng.uniform(1.0, 3.0, size=count))
    m0 = jnp.asarray(rng.normal(size=(count, 6)))
    g0 = jax.vmap(lievi.SE3.exp)(jnp.asarray(rng.normal(size=(count, 6))))
    return inertia, mass, g0, m0


def _run(inertia, mass, g0, m0):
    body = lievi.RigidBodySE3(inertia, mass)
    return lievi.simulate(
        body, lievi.DEP(chart="cayley"), g0, m0, h=0.5, n_steps=8, save=lievi.Save(every=4)
    )


def test_vmap_of_simulate_equals_each_body():
    """`jax.vmap(simulate)` of SE(3) bodies by Cayley DEP steps, at a step that takes some
    bodies past the fixed Newton iterations (the solve's loop runs): each body's
    trajectory as its own `simulate` gives it, to round-off. One body alone takes the
    whole-array Newton loop, the vmapped bodies the batch kernel's solve: their iterations
    are `simulate_batch`'s on the same bodies, exactly."""
    inertia, mass, g0, m0 = se3_bodies(3)
    batched = jax.jit(jax.vmap(_run))(inertia, mass, g0, m0)
    assert int(jnp.max(batched.stats["newton_iterations"])) > 3  # the fixed iterations
    one_run = jax.jit(_run)
    for i in range(len(mass)):
        one = one_run(inertia[i], mass[i], g0[i], m0[i])
        np.testing.assert_allclose(batched.m[i], one.m, rtol=ROUNDOFF, atol=ROUNDOFF)
        np.testing.assert_allclose(batched.g[i], one.g, rtol=ROUNDOFF, atol=ROUNDOFF)
    bodies = jax.vmap(lievi.RigidBodySE3)(inertia, mass)
    together = lievi.simulate_batch(
        bodies, lievi.DEP(chart="cayley"), g0, m0, h=0.5, n_steps=8, save=lievi.Save(every=4)
    )
    np.testing.assert_array_equal(
        batched.stats["newton_iterations"], together.stats["newton_iterations"]
    )


@pytest.mark.extended
def test_vmap_of_simulate_derivatives():
    """The same runs' gradient (reverse mode) and tangent (forward mode) under `jax.vmap`:
    each body's own, to 1e-10 relative (the solve is not differentiated; the root's
    derivative is the implicit function theorem's)."""
    inertia, mass, g0, m0 = se3_bodies(3)

    def final(inertia, m0, mass, g0):
        return jnp.sum(_run(inertia, mass, g0, m0).m[-1] ** 2)

    def tangent_of(inertia, m0, mass, g0):
        return jax.jvp(lambda m: final(inertia, m, mass, g0), (m0,), (jnp.ones_like(m0),))[1]

    gradient = jax.grad(final, argnums=(0, 1))
    grads = jax.jit(jax.vmap(gradient))(inertia, m0, mass, g0)
    tangents = jax.jit(jax.vmap(tangent_of))(inertia, m0, mass, g0)
    one_gradient, one_tangent = jax.jit(gradient), jax.jit(tangent_of)
    for i in range(len(mass)):
        expected = one_gradient(inertia[i], m0[i], mass[i], g0[i])
        for got, want in zip(grads, expected):
            np.testing.assert_allclose(got[i], want, rtol=1e-10)
        want = one_tangent(inertia[i], m0[i], mass[i], g0[i])
        np.testing.assert_allclose(tangents[i], want, rtol=1e-10)
