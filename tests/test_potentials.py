"""Potentials and broken symmetry (paper §7): the heavy top, the 3-D pendulum, SO(4).

Checks (float64): order against a DOP853 reference with the same potential; the exact
discrete conservation laws of the reduced dynamics (`|Γ|²`, `Π·Γ = e₃·(gΠ)`, `Π₃` of a
Lagrange top); bounded energy; the DEL residual by autodiff of the discrete Lagrangian
including `V`; zero potential = free body; the right-invariant mirror image; gradients
with respect to the potential's parameters; bad input.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem, random_rotation
from lievi import diagnostics as dg

ORDER_TOLERANCE = 0.1

# An asymmetric top with an off-axis centre of mass (gravity 1: nondimensional units).
INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
RHO = jnp.array([0.3, -0.2, 0.5])
M0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])


def asymmetric_top():
    return lievi.heavy_top(INERTIA, 1.0, RHO, gravity=1.0)


def g0_tilted():
    return lievi.SO3.exp(jnp.array([0.4, -0.3, 0.2]))


def observed_order(system, integrator, g0, m0, T, hs):
    g_ref, m_ref = lievi.reference_solution(system, g0, m0, [0.0, T])
    errors = []
    for h in hs:
        sol = lievi.simulate(system, integrator, g0, m0, h=h, n_steps=int(round(T / h)))
        errors.append(
            max(np.max(np.abs(sol.m[-1] - m_ref[-1])), np.max(np.abs(sol.g[-1] - g_ref[-1])))
        )
    return np.polyfit(np.log(hs), np.log(errors), 1)[0], errors


SECOND_ORDER = (
    lievi.DEP(chart="exp"),
    lievi.DEP(chart="cayley"),
    lievi.MoserVeselov(),
    lievi.LiePoissonSplitting(),
)
SECOND_ORDER_IDS = ("dep-exp", "dep-cayley", "moser-veselov", "splitting")


@pytest.mark.parametrize(
    "integrator",
    (
        pytest.param(SECOND_ORDER[0], marks=pytest.mark.extended),  # 10 s
        SECOND_ORDER[1],
        pytest.param(SECOND_ORDER[2], marks=pytest.mark.slow),
        SECOND_ORDER[3],
    ),
    ids=SECOND_ORDER_IDS,
)
def test_second_order_heavy_top(integrator):
    hs = [0.1 / 2**k for k in range(3)]
    order, errors = observed_order(asymmetric_top(), integrator, g0_tilted(), M0, 2.0, hs)
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.parametrize(
    "integrator",
    (lievi.RK4(), pytest.param(lievi.Composition(lievi.DEP(), 4), marks=pytest.mark.slow)),
    ids=("rk4", "composition-dep-4"),
)
def test_fourth_order_heavy_top(integrator):
    hs = [0.2 / 2**k for k in range(3)]
    order, errors = observed_order(asymmetric_top(), integrator, g0_tilted(), M0, 2.0, hs)
    assert abs(order - 4) <= 0.2, (order, errors)


def reduced_invariants(sol):
    """`|Γ|² − 1`, `Π·Γ` and `e₃·(gΠ)` along a run (Γ = gᵀe₃, the advected vertical)."""
    gamma = sol.g[:, 2, :]
    return (
        jnp.sum(gamma**2, axis=1) - 1,
        jnp.sum(sol.m * gamma, axis=1),
        jnp.einsum("tij,tj->ti", sol.g, sol.m)[:, 2],
    )


@pytest.mark.parametrize("integrator", SECOND_ORDER, ids=SECOND_ORDER_IDS)
def test_reduced_invariants_over_5000_steps(integrator):
    top = asymmetric_top()
    sol = lievi.simulate(
        top, integrator, g0_tilted(), M0, h=0.05, n_steps=5000, save=lievi.Save(every=10)
    )
    assert sol.result == lievi.RESULTS.successful
    norm, pi_gamma, vertical = reduced_invariants(sol)
    assert jnp.max(jnp.abs(norm)) <= ROUNDOFF
    assert dg.relative_drift(pi_gamma) <= ROUNDOFF
    assert jnp.max(jnp.abs(vertical - pi_gamma)) <= ROUNDOFF  # Π·Γ = e₃·(gΠ)
    energy = dg.energy(top, sol.g, sol.m)
    # Bounded, O(h²), and no drift: the second half oscillates like the first.
    half = energy.shape[0] // 2
    first, second = energy[:half] - energy[0], energy[half:] - energy[0]
    assert jnp.max(jnp.abs(first)) < 1e-2
    assert jnp.max(jnp.abs(second)) <= 1.5 * jnp.max(jnp.abs(first))


@pytest.mark.slow
@pytest.mark.parametrize("n_steps", (100_000, 1_000_000), ids=("1e5", "1e6"))
def test_heavy_top_long_run_dep(n_steps):
    top = asymmetric_top()
    sol = lievi.simulate(
        top,
        lievi.DEP(),
        g0_tilted(),
        M0,
        h=0.05,
        n_steps=n_steps,
        save=lievi.Save(every=n_steps // 1000),
    )
    assert sol.result == lievi.RESULTS.successful
    norm, pi_gamma, vertical = reduced_invariants(sol)
    assert jnp.max(jnp.abs(norm)) <= ROUNDOFF
    assert dg.relative_drift(pi_gamma) <= ROUNDOFF
    assert jnp.max(jnp.abs(vertical - pi_gamma)) <= ROUNDOFF
    energy = dg.energy(top, sol.g, sol.m) - dg.energy(top, g0_tilted(), M0)
    tenth = energy.shape[0] // 10
    assert jnp.max(jnp.abs(energy[-tenth:])) <= 1.5 * jnp.max(jnp.abs(energy[:tenth]))


@pytest.mark.extended  # 17 s
def test_lagrange_top_keeps_its_spin():
    """The variational methods are equivariant under rotations about the symmetry axis, so
    (discrete Noether) they keep `Π₃`. The splitting does not: its sub-flows about the first
    and second axes break that symmetry (it keeps `Π₃` only to O(h²))."""
    top = lievi.heavy_top(jnp.array([1.0, 1.0, 0.4]), 2.0, jnp.array([0.0, 0.0, 0.6]), gravity=1.0)
    m0 = jnp.array([0.3, -0.1, 2.0])
    for integrator in (lievi.DEP(), lievi.DEP(chart="cayley"), lievi.MoserVeselov()):
        sol = lievi.simulate(
            top, integrator, g0_tilted(), m0, h=0.05, n_steps=2000, save=lievi.Save(every=10)
        )
        assert dg.relative_drift(sol.m[:, 2]) <= ROUNDOFF, type(integrator).__name__


@pytest.mark.parametrize("integrator", SECOND_ORDER[:3], ids=SECOND_ORDER_IDS[:3])
def test_del_residual_with_potential(integrator):
    top, h = asymmetric_top(), 0.05
    sol = lievi.simulate(top, integrator, g0_tilted(), M0, h=h, n_steps=100)
    residual = dg.del_residual(top, integrator, sol.g, h)
    assert jnp.max(jnp.abs(residual)) <= ROUNDOFF


def test_del_residual_detects_a_missing_kick():
    """The check can fail: dropping the second half kick breaks the DEL equations."""

    class HalfKick(lievi.DEP):
        def step(self, system, g, m, h):
            return self.free_step(system, g, system.kick(g, m, h / 2), h)

    top, h = asymmetric_top(), 0.05
    sol = lievi.simulate(top, HalfKick(), g0_tilted(), M0, h=h, n_steps=20)
    assert jnp.max(jnp.abs(dg.del_residual(top, lievi.DEP(), sol.g, h))) > 1e-6


@pytest.mark.extended  # 10 s
def test_start_from_two_configurations():
    top, h = asymmetric_top(), 0.05
    sol = lievi.simulate(top, lievi.DEP(), g0_tilted(), M0, h=h, n_steps=3)
    again = lievi.simulate(top, lievi.DEP(), sol.g[0], g1=sol.g[1], h=h, n_steps=3)
    assert jnp.max(jnp.abs(again.m - sol.m)) <= ROUNDOFF


ZERO_POTENTIALS = (
    (lievi.UniformGravity(0.0, RHO), "zero-mass"),
    (lambda g: 0.0 * g[0, 0], "zero-callable"),
)
ZERO_POTENTIAL_EXTENDED = (
    "dep-exp-zero-mass",  # 12 s
    "dep-exp-zero-callable",  # 11 s
    "moser-veselov-zero-mass",  # 9 s
)


@pytest.mark.parametrize(
    "integrator, potential",
    [
        pytest.param(
            integrator,
            potential,
            id=f"{name}-{kind}",
            marks=pytest.mark.extended if f"{name}-{kind}" in ZERO_POTENTIAL_EXTENDED else (),
        )
        for integrator, name in zip(SECOND_ORDER + (lievi.RK4(),), SECOND_ORDER_IDS + ("rk4",))
        for potential, kind in ZERO_POTENTIALS
    ],
)
def test_zero_potential_is_the_free_body(potential, integrator):
    body, g0, m0 = hlw_problem()
    free = lievi.simulate(body, integrator, g0, m0, h=0.1, n_steps=50)
    with_zero = lievi.simulate(
        lievi.RigidBody(body.inertia, potential=potential), integrator, g0, m0, h=0.1, n_steps=50
    )
    assert jnp.max(jnp.abs(with_zero.m - free.m)) <= 1e-14
    assert jnp.max(jnp.abs(with_zero.g - free.g)) <= 1e-14


def test_torque_is_gamma_cross_rho():
    """The autodiff force of `UniformGravity` is the heavy top's torque `m γ Γ × ρ`."""
    top = lievi.heavy_top(INERTIA, 1.7, RHO, gravity=9.81)
    g = random_rotation(np.random.default_rng(0), 3)
    expected = 1.7 * 9.81 * jnp.cross(g[2], RHO)
    assert jnp.max(jnp.abs(top.force(g) - expected)) <= 1e-13


@pytest.mark.extended  # 11 s
def test_three_d_pendulum():
    """A slender rod on a spherical joint: inertia about the pivot, long arm."""
    length, mass = 1.0, 1.0
    inertia = jnp.array([mass * length**2 / 3, mass * length**2 / 3, 1e-2])
    pendulum = lievi.heavy_top(inertia, mass, jnp.array([0.0, 0.0, -length / 2]), gravity=9.81)
    g0 = lievi.SO3.exp(jnp.array([1.2, 0.3, 0.0]))  # swung out by ~70°
    m0 = inertia * jnp.array([0.0, 1.0, 0.5])
    h = 0.01
    sol = lievi.simulate(
        pendulum, lievi.DEP(), g0, m0, h=h, n_steps=2000, save=lievi.Save(every=10)
    )
    assert sol.result == lievi.RESULTS.successful
    norm, pi_gamma, _ = reduced_invariants(sol)
    assert jnp.max(jnp.abs(norm)) <= ROUNDOFF
    assert dg.relative_drift(pi_gamma) <= ROUNDOFF
    assert dg.relative_drift(dg.energy(pendulum, sol.g, sol.m)) < 1e-3
    short = lievi.simulate(pendulum, lievi.DEP(), g0, m0, h=h, n_steps=50)
    assert jnp.max(jnp.abs(dg.del_residual(pendulum, lievi.DEP(), short.g, h))) <= ROUNDOFF


@pytest.mark.extended  # 19 s
def test_potential_on_son():
    """A heavy generalized rigid body on SO(4): gravity along the last axis."""
    rng = np.random.default_rng(7)
    body = lievi.GeneralizedRigidBody(
        jnp.array([0.7, 1.1, 1.6, 0.9]),
        potential=lievi.UniformGravity(1.0, jnp.array(rng.normal(size=4)), 1.0),
    )
    g0, m0, h = random_rotation(rng, 4), jnp.asarray(rng.normal(size=6)), 0.05
    for integrator in (lievi.DEP(), lievi.MoserVeselov(), lievi.LiePoissonSplitting()):
        sol = lievi.simulate(body, integrator, g0, m0, h=h, n_steps=400)
        assert sol.result == lievi.RESULTS.successful
        # The symmetry left is SO(3) acting on the first three world axes: the spatial
        # momentum g m̂ gᵀ keeps its block in those axes.
        spatial = jnp.einsum("tij,tjk,tlk->til", sol.g, body.group.hat(sol.m), sol.g)[:, :3, :3]
        assert dg.relative_drift(spatial.reshape(spatial.shape[0], -1)) <= ROUNDOFF
        assert jnp.max(dg.orthogonality_defect(body, sol.g)) <= ROUNDOFF
        if isinstance(integrator, lievi.AbstractVariationalIntegrator):
            residual = dg.del_residual(body, integrator, sol.g[:60], h)
            assert jnp.max(jnp.abs(residual)) <= ROUNDOFF


@pytest.mark.extended  # 13 s
def test_right_invariant_mirror_image():
    """Right-invariant `(g_k, μ_k)` = left-invariant `(g_k⁻¹, −μ_k)` for `l(−ξ)`, `V(g⁻¹)`."""
    inertia = jnp.array([1.5, 1.0, 0.7])

    def l(xi):
        return 0.5 * jnp.dot(xi, inertia * xi) + 0.1 * xi[0] ** 3  # not even in ξ

    def V(g):
        return jnp.dot(g[2], RHO) + 0.3 * g[0, 1] ** 2

    right = lievi.LieLagrangian(lievi.SO3, l, side="right", potential=V)
    left = lievi.LieLagrangian(
        lievi.SO3, lambda xi: l(-xi), side="left", potential=lambda g: V(g.T)
    )
    g0, m0, h = g0_tilted(), jnp.array([0.4, -0.2, 0.6]), 0.05
    for chart in ("exp", "cayley"):
        sol_r = lievi.simulate(right, lievi.DEP(chart=chart), g0, m0, h=h, n_steps=100)
        sol_l = lievi.simulate(left, lievi.DEP(chart=chart), g0.T, -m0, h=h, n_steps=100)
        assert jnp.max(jnp.abs(sol_r.g - jnp.swapaxes(sol_l.g, 1, 2))) <= ROUNDOFF
        assert jnp.max(jnp.abs(sol_r.m + sol_l.m)) <= ROUNDOFF
        residual = dg.del_residual(right, lievi.DEP(chart=chart), sol_r.g, h)
        assert jnp.max(jnp.abs(residual)) <= ROUNDOFF
    order, errors = observed_order(right, lievi.DEP(), g0, m0, 1.0, [0.05 / 2**k for k in range(3)])
    assert abs(order - 2) <= ORDER_TOLERANCE, (order, errors)


@pytest.mark.extended  # 8 s
def test_gradients_match_finite_differences():
    """d/d(I, mρ, Π₀) of a loss of a 1000-step heavy-top run, against central differences."""
    g0, h, n = g0_tilted(), 0.01, 1000

    def loss(inertia, m_rho, m0):
        top = lievi.RigidBody(inertia, potential=lievi.UniformGravity(1.0, m_rho, 1.0))
        sol = lievi.simulate(top, lievi.DEP(), g0, m0, h=h, n_steps=n, save=lievi.Save(every=100))
        return jnp.sum(jnp.sin(sol.g)) + jnp.sum(sol.m**2)

    args = (INERTIA, RHO, M0)
    grads = jax.jit(jax.grad(loss, argnums=(0, 1, 2)))(*args)
    f = jax.jit(loss)
    rng = np.random.default_rng(3)
    for k, grad in enumerate(grads):
        direction = jnp.asarray(rng.normal(size=args[k].shape))
        eps = 1e-4
        plus = list(args)
        minus = list(args)
        plus[k] = args[k] + eps * direction
        minus[k] = args[k] - eps * direction
        # 4th-order central difference
        plus2, minus2 = list(args), list(args)
        plus2[k] = args[k] + 2 * eps * direction
        minus2[k] = args[k] - 2 * eps * direction
        fd = (8 * (f(*plus) - f(*minus)) - (f(*plus2) - f(*minus2))) / (12 * eps)
        exact = jnp.dot(grad, direction)
        assert abs(exact - fd) <= 1e-6 * abs(exact), (k, exact, fd)


def test_bad_potentials():
    with pytest.raises(ValueError, match="`mass`"):
        lievi.UniformGravity(-1.0, RHO)
    with pytest.raises(ValueError, match="`center_of_mass`"):
        lievi.UniformGravity(1.0, jnp.array([0.0, jnp.nan, 1.0]))
    with pytest.raises(ValueError, match="`center_of_mass`"):
        lievi.UniformGravity(1.0, jnp.ones((3, 3)))
    with pytest.raises(ValueError, match="`potential`.*scalar"):
        lievi.RigidBody(INERTIA, potential=lambda g: g[0])
    with pytest.raises(ValueError, match="`potential`"):
        lievi.RigidBody(INERTIA, potential="gravity")
    with pytest.raises(ValueError, match="PreprocessedMoserVeselov"):
        lievi.simulate(
            asymmetric_top(), lievi.PreprocessedMoserVeselov(4), jnp.eye(3), M0, h=0.1, n_steps=2
        )


def test_nonfinite_potential_is_reported():
    body = lievi.RigidBody(INERTIA, potential=lambda g: jnp.sqrt(g[0, 0] - 2.0))  # NaN on SO(3)
    sol = lievi.simulate(body, lievi.DEP(), jnp.eye(3), M0, h=0.1, n_steps=5, throw=False)
    assert sol.result == lievi.RESULTS.nonfinite
    assert int(sol.stats["failed_step"]) == 0
    with pytest.raises(Exception, match="non-finite|NaN|nonfinite"):
        lievi.simulate(body, lievi.LiePoissonSplitting(), jnp.eye(3), M0, h=0.1, n_steps=5)


@pytest.mark.extended  # 10 s
def test_potential_parameters_under_vmap():
    """A batch of tops with their own centres of mass, by `jax.vmap(simulate)`."""
    rhos = jnp.asarray(np.random.default_rng(1).normal(size=(4, 3)))

    def run(rho):
        top = lievi.heavy_top(INERTIA, 1.0, rho, gravity=1.0)
        return lievi.simulate(top, lievi.DEP(), g0_tilted(), M0, h=0.05, n_steps=20, throw=False)

    batched = jax.vmap(run)(rhos)
    for k in range(4):
        single = run(rhos[k])
        assert jnp.max(jnp.abs(batched.m[k] - single.m)) <= ROUNDOFF


def test_heavy_top_inertia_about_the_center_of_mass():
    """`inertia_about="center_of_mass"` applies the parallel-axis theorem,
    `I_O = I_C + m(|ρ|²1 − ρρᵀ)`: principal moments stay moments for `ρ` on a principal
    axis (the fast path still applies), a full tensor otherwise; the same top either way."""
    moments_c, mass = jnp.array([0.3, 0.4, 0.5]), 2.0
    on_axis = jnp.array([0.0, 0.0, 0.6])
    top = lievi.heavy_top(moments_c, mass, on_axis, gravity=1.0, inertia_about="center_of_mass")
    np.testing.assert_allclose(top.inertia, moments_c + mass * jnp.array([0.36, 0.36, 0.0]))
    assert lievi.advanced.has_fast_path(top, lievi.DEP())
    off_axis = jnp.array([0.1, -0.2, 0.6])
    top = lievi.heavy_top(moments_c, mass, off_axis, gravity=1.0, inertia_about="center_of_mass")
    expected = jnp.diag(moments_c) + mass * (
        jnp.dot(off_axis, off_axis) * jnp.eye(3) - jnp.outer(off_axis, off_axis)
    )
    np.testing.assert_allclose(top.inertia, expected, rtol=0, atol=ROUNDOFF)
    same = lievi.heavy_top(expected, mass, off_axis, gravity=1.0)
    kwargs = dict(h=0.05, n_steps=20)
    a = lievi.simulate(top, lievi.DEP(), jnp.eye(3), jnp.array([0.2, 0.1, 0.5]), **kwargs)
    b = lievi.simulate(same, lievi.DEP(), jnp.eye(3), jnp.array([0.2, 0.1, 0.5]), **kwargs)
    np.testing.assert_array_equal(a.m, b.m)
    with pytest.raises(ValueError, match="`inertia_about` must be"):
        lievi.heavy_top(moments_c, mass, on_axis, inertia_about="com")


def test_one_body_heavy_top_takes_the_batch_newton_policy():
    """`simulate` of one body, `simulate_batch` and `Tuning(fast=False)` run the kick
    kernel's free step with one Newton policy: the batch's fixed iterations (in a loop for
    one body), then a test. At a tiny step the first iterate already meets the tolerance;
    every path still takes the fixed iterations, and the three give the same iterations
    and the same trajectory to round-off (float64, 1e-13)."""
    top, dep = asymmetric_top(), lievi.DEP(chart="exp")
    g0, m0 = g0_tilted(), M0
    one = lievi.simulate(top, dep, g0, m0, h=1e-6, n_steps=4)
    batch = lievi.simulate_batch(top, dep, g0[None], m0[None], h=1e-6, n_steps=4)
    fixed = lievi.simulate_batch(
        top,
        dep,
        g0[None],
        m0[None],
        h=1e-6,
        n_steps=4,
        tuning=lievi.advanced.Tuning(fast=False),
    )
    for run in (batch, fixed):
        np.testing.assert_array_equal(
            run.stats["newton_iterations"][0], one.stats["newton_iterations"]
        )
        np.testing.assert_allclose(one.m, run.m[0], rtol=0, atol=1e-13)
    # The free step's fixed iterations (3, exp chart) and no more.
    assert np.all(one.stats["newton_iterations"][1:] == 3)


@pytest.mark.parametrize("rho", [(0.0, 0.0, 0.5), (0.1, -0.2, 0.5)], ids=["on-axis", "off-axis"])
def test_heavy_top_about_the_centre_of_mass_keeps_float32(rho):
    """The parallel-axis shift is made in the inputs' dtype: a float32 top stays float32
    (under x64 a default identity had made its inertia, and its runs, float64)."""
    moments = jnp.array([0.8, 0.8, 1.0], jnp.float32)
    top = lievi.heavy_top(
        moments, 1.0, jnp.array(rho, jnp.float32), 1.0, inertia_about="center_of_mass"
    )
    assert top.inertia.dtype == jnp.float32
