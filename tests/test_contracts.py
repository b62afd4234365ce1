"""Contracts that must hold alike eagerly and traced, on one body and on a batch
(docs/guarantees.md): parameter checks, a potential's value, unit invariance of forced
steps, group membership of float32 output, `Solution.advected`, batched systems.

float64 unless a test says float32.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi

SUCCESS, INVALID = int(lievi.RESULTS.successful), int(lievi.RESULTS.invalid_input)
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
M0 = jnp.array([0.3, -0.2, 0.5])
RHO = jnp.array([0.1, 0.0, 0.5])
EYE4 = jnp.eye(4)
TENSOR = jnp.diag(jnp.array([2.0, 1.5, 1.0, 3.0, 3.0, 3.0]))


# ---- parameter checks: one definition, eager and traced ---------------------------------

ASYMMETRIC = TENSOR.at[0, 1].set(0.5)
INDEFINITE = TENSOR.at[5, 5].set(-1.0)


def se3_tensor(p):
    return lievi.RigidBodySE3(tensor=p)


def se3_mass(p):
    return lievi.RigidBodySE3(INERTIA, p)


def top_mass(p):
    return lievi.RigidBody(INERTIA, lievi.UniformGravity(p, RHO, 1.0))


def se3_gravity_mass(p):
    return lievi.RigidBodySE3(INERTIA, 2.0, potential=lievi.UniformGravitySE3(p))


def central_mu(p):
    points = jnp.array([[0.5, 0.0, 0.0], [-0.5, 0.0, 0.0]])
    return lievi.RigidBodySE3(INERTIA, 2.0, potential=lievi.CentralGravity(p, jnp.ones(2), points))


CASES = {
    "se3-asymmetric": (se3_tensor, TENSOR, ASYMMETRIC),
    "se3-indefinite": (se3_tensor, TENSOR, INDEFINITE),
    "se3-negative-definite": (se3_tensor, TENSOR, -TENSOR),
    "se3-negative-mass": (se3_mass, 2.0, -2.0),
    "uniform-gravity-negative-mass": (top_mass, 1.0, -1.0),
    "uniform-gravity-se3-negative-mass": (se3_gravity_mass, 1.0, -1.0),
    "central-gravity-negative-mu": (central_mu, 1.0, -1.0),
}


def start(system):
    n, d = system.group.matrix_dim, system.group.algebra_dim
    g0 = jnp.eye(n).at[:3, 3].set(jnp.array([0.0, 0.0, 5.0])) if n == 4 else jnp.eye(n)
    return g0, 0.1 * jnp.arange(1.0, d + 1.0)


# One case per class under -m extended (8–39 s each), the others under -m slow: each
# compiles a run.
EXTENDED_CASES = ("se3-indefinite", "uniform-gravity-negative-mass", "central-gravity-negative-mu")


@pytest.mark.parametrize(
    "name",
    [
        pytest.param(n, marks=pytest.mark.extended if n in EXTENDED_CASES else pytest.mark.slow)
        for n in CASES
    ],
)
def test_parameter_check_eager_and_traced(name):
    """A bad parameter raises eagerly and gives `invalid_input` under `vmap`/`jit`."""
    make, good, bad = CASES[name]
    with pytest.raises(ValueError):
        make(bad)
    g0, m0 = start(make(good))

    def run(p):
        system = make(p)
        return lievi.simulate(system, lievi.DEP(), g0, m0, h=0.01, n_steps=2, throw=False).result

    params = jnp.stack([jnp.asarray(good, float), jnp.asarray(bad, float)])
    np.testing.assert_array_equal(jax.vmap(run)(params), [SUCCESS, INVALID])
    assert int(jax.jit(run)(params[1])) == INVALID


@pytest.mark.extended  # 17 s
def test_parameter_check_batched_fast_path():
    """`simulate_batch` on a vmapped batch of heavy tops, one with a negative mass."""
    masses = jnp.array([1.0, -1.0, 0.5])
    tops = jax.vmap(top_mass)(masses)
    g0, m0 = jnp.broadcast_to(jnp.eye(3), (3, 3, 3)), jnp.broadcast_to(M0, (3, 3))
    assert lievi.advanced.has_fast_path(tops, lievi.DEP(), system_axis=0)
    for fast in (True, False):
        sol = lievi.simulate_batch(
            tops,
            lievi.DEP(),
            g0,
            m0,
            h=0.05,
            n_steps=4,
            system_axis=0,
            save=lievi.Save(every=4),
            tuning=lievi.advanced.Tuning(fast=fast),
            throw=False,
        )
        np.testing.assert_array_equal(sol.result, [SUCCESS, INVALID, SUCCESS])


# ---- a potential whose value is not finite ----------------------------------------------


@pytest.mark.extended  # 9 s
def test_nonfinite_potential_value_is_reported():
    """A log barrier `V = −k log g₃₃`: past horizontal its value is NaN while its force is
    finite. The run reports `nonfinite` (one body and batch), not `successful`."""
    body = lievi.RigidBody(jnp.ones(3), potential=lambda g: -1e-3 * jnp.log(g[2, 2]))
    g0 = lievi.SO3.exp(jnp.array([np.deg2rad(80.0), 0.0, 0.0]))
    m0 = jnp.array([5.0, 0.0, 0.0])  # 0.5 rad a step: from 80° to 108° in one step
    kwargs = dict(h=0.1, n_steps=4, throw=False)
    for integrator in (lievi.DEP(), lievi.LiePoissonSplitting(), lievi.RK4()):
        sol = lievi.simulate(body, integrator, g0, m0, **kwargs)
        assert int(sol.result) == int(lievi.RESULTS.nonfinite), integrator
        assert int(sol.stats["failed_step"]) == 0
    batch = lievi.simulate_batch(body, lievi.DEP(), g0[None], m0[None], **kwargs)
    np.testing.assert_array_equal(batch.result, [lievi.RESULTS.nonfinite])


# ---- forced steps are unit-invariant ----------------------------------------------------


@pytest.mark.extended  # 15 s each
@pytest.mark.parametrize("integrator", [lievi.DEP(), lievi.LiePoissonSplitting()])
def test_damping_is_unit_invariant(integrator):
    """Damping `−cΩ` makes the end-of-step kick implicit; its Newton test is relative, so
    the run in units scaled by `s` (`(I, Π, c) → (sI, sΠ, sc)`) is the unscaled run,
    rescaled, to round-off. (An absolute test accepted the explicit guess for `s ≤ 1e-9`:
    off by 1e-3.)"""
    c = 0.3

    def run(scale):
        body = lievi.RigidBody(scale * INERTIA)
        damping = lievi.ForceLaw(lambda t, g, m, a: -a * body.velocity(m))
        return lievi.simulate(
            body,
            integrator,
            jnp.eye(3),
            scale * M0,
            h=0.05,
            n_steps=200,
            forcing=damping,
            args=scale * c,
        )

    plain = run(1.0)
    for scale in (1e-6, 1e-9, 1e-12):
        small = run(scale)
        np.testing.assert_allclose(small.m / scale, plain.m, rtol=0, atol=1e-12 * 0.6)
        np.testing.assert_allclose(small.g, plain.g, rtol=0, atol=1e-12)


# ---- float32 output is in the group -----------------------------------------------------


def f32(x):
    return jnp.asarray(x, jnp.float32)


@pytest.mark.slow
def test_float32_run_continues_from_its_output():
    """5000 float32 DEP steps, one body and a batch: the last state is accepted as the
    start of the next run (eagerly and traced), and its membership defect is at round-off."""
    body = lievi.RigidBody(f32(INERTIA))
    tolerance = lievi._checks.membership_tolerance(jnp.float32)
    kwargs = dict(h=f32(0.05), n_steps=5000, save=lievi.Save(every=5000))
    sol = lievi.simulate(body, lievi.DEP(), jnp.eye(3, dtype=jnp.float32), f32(M0 * 4), **kwargs)
    batch = lievi.simulate_batch(
        body, lievi.DEP(), jnp.eye(3, dtype=jnp.float32)[None], f32(M0 * 4)[None], **kwargs
    )
    for g, m in ((sol.g[-1], sol.m[-1]), (batch.g[0, -1], batch.m[0, -1])):
        assert g.dtype == jnp.float32
        assert float(lievi.SO3.membership_defect(g.astype(float))) < tolerance / 4
        more = lievi.simulate(body, lievi.DEP(), g, m, h=f32(0.05), n_steps=2)
        assert int(more.result) == SUCCESS
        traced = jax.jit(lambda g: body.element_valid(g))(g)
        assert bool(traced)


@pytest.mark.extended  # 12 s
def test_membership_tolerance_is_the_same_eager_and_traced():
    """An element just inside the float32 tolerance is accepted eagerly and traced, one
    just outside rejected by both (one tolerance, defined once)."""
    body = lievi.RigidBody(f32(INERTIA))
    tolerance = lievi._checks.membership_tolerance(jnp.float32)
    for factor, accepted in ((0.5, True), (2.0, False)):
        g = jnp.eye(3).at[0, 0].add(factor * tolerance / 2).astype(jnp.float32)
        assert bool(jax.jit(lambda g: body.element_valid(g))(g)) == accepted
        sol = jax.jit(
            lambda g: lievi.simulate(
                body, lievi.DEP(), g, f32(M0), h=f32(0.1), n_steps=1, throw=False
            )
        )(g)
        assert (int(sol.result) == SUCCESS) == accepted
        batch = (
            lievi.simulate_batch(
                body,
                lievi.DEP(),
                g[None],
                f32(M0)[None],
                h=f32(0.1),
                n_steps=1,
                throw=False,
                save=lievi.Save(every=1),
            )
            if accepted
            else None
        )
        if accepted:
            lievi.simulate(body, lievi.DEP(), g, f32(M0), h=f32(0.1), n_steps=1)
            assert int(batch.result[0]) == SUCCESS
        else:
            with pytest.raises(ValueError, match="not in the group"):
                lievi.simulate(body, lievi.DEP(), g, f32(M0), h=f32(0.1), n_steps=1)
            with pytest.raises(ValueError, match="not in the group"):
                lievi.simulate_batch(
                    body,
                    lievi.DEP(),
                    g[None],
                    f32(M0)[None],
                    h=f32(0.1),
                    n_steps=1,
                    save=lievi.Save(every=1),
                )


# ---- Solution.advected ------------------------------------------------------------------


@pytest.mark.extended  # 12 s
def test_advected_whenever_g_is_saved():
    """`Solution.advected` is `gᵀe₃` whenever `g` is saved and the potential has an
    advected direction: `simulate`, and `simulate_batch` on both paths."""
    top = lievi.heavy_top(INERTIA, 1.0, RHO, gravity=1.0)
    sol = lievi.simulate(top, lievi.DEP(), jnp.eye(3), M0, h=0.05, n_steps=6)
    np.testing.assert_array_equal(sol.advected, sol.g[:, 2, :])
    g0, m0 = jnp.eye(3)[None], M0[None]
    for fast in (True, False):
        batch = lievi.simulate_batch(
            top,
            lievi.DEP(),
            g0,
            m0,
            h=0.05,
            n_steps=6,
            save=lievi.Save(stats=False, every=2),
            tuning=lievi.advanced.Tuning(fast=fast),
        )
        assert batch.advected is not None
        np.testing.assert_array_equal(batch.advected, batch.g[..., 2, :])
    free = lievi.simulate(lievi.RigidBody(INERTIA), lievi.DEP(), jnp.eye(3), M0, h=0.05, n_steps=2)
    assert free.advected is None


# ---- batched systems without `system_axis` ----------------------------------------------


@pytest.mark.extended  # 16 s
def test_vmapped_system_without_system_axis():
    """A system built with `jax.vmap` and no `system_axis`: the axis is inferred (its
    leaves are one dimension larger than one system's, with the batch's size), on both
    paths and in `has_fast_path`."""
    rng = np.random.default_rng(3)
    inertias = jnp.asarray(rng.uniform(0.5, 2.0, size=(4, 3)))
    bodies = jax.vmap(lievi.RigidBody)(inertias)
    g0, m0 = jnp.broadcast_to(jnp.eye(3), (4, 3, 3)), jnp.asarray(rng.normal(size=(4, 3)))
    assert lievi.advanced.has_fast_path(bodies, lievi.DEP())
    kwargs = dict(h=0.05, n_steps=5)
    for fast in (True, False):
        inferred = lievi.simulate_batch(
            bodies, lievi.DEP(), g0, m0, tuning=lievi.advanced.Tuning(fast=fast), **kwargs
        )
        explicit = lievi.simulate_batch(
            bodies,
            lievi.DEP(),
            g0,
            m0,
            tuning=lievi.advanced.Tuning(fast=fast),
            system_axis=0,
            **kwargs,
        )
        np.testing.assert_array_equal(inferred.m, explicit.m)


def test_vmapped_system_of_another_batch_size_says_what_to_pass():
    bodies = jax.vmap(lievi.RigidBody)(jnp.ones((4, 3)))
    g0, m0 = jnp.broadcast_to(jnp.eye(3), (5, 3, 3)), jnp.ones((5, 3))
    with pytest.raises(ValueError, match="system_axis"):
        lievi.simulate_batch(
            bodies, lievi.DEP(), g0, m0, h=0.05, n_steps=2, save=lievi.Save(every=2)
        )


def test_integer_potential_is_a_clear_error():
    """A potential returning an integer fails at construction with lievi's own message, not
    inside JAX's gradient."""
    with pytest.raises(ValueError, match="real floating-point"):
        lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]), potential=lambda g: 0)


def test_energy_of_a_system_with_a_potential_needs_g():
    """`diagnostics.energy` is jit-compiled; its argument check still raises a `ValueError`
    that names `g` (raised while tracing, before anything is compiled)."""
    top = lievi.RigidBody(jnp.ones(3), lievi.UniformGravity(1.0, jnp.ones(3)))
    with pytest.raises(ValueError, match="pass `g`"):
        lievi.diagnostics.energy(top, None, jnp.ones((5, 3)))
    energy = lievi.diagnostics.energy(
        top, jnp.broadcast_to(jnp.eye(3), (5, 3, 3)), jnp.ones((5, 3))
    )
    assert energy.shape == (5,)
