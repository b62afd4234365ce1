"""External forces and controls: the discrete Lagrange–d'Alembert principle.

Checks (float64 unless stated): zero forcing = the unforced run, bit for bit; order against
a DOP853 reference with the same forcing (force law and held control); the forced discrete
Noether theorem per step; dissipation (monotone energy decay to rest, the discrete work
balance at O(h²)); gradients with respect to a whole control sequence against central
differences, jacfwd = jacrev, gradients of a force law's parameters; batches with per-body
controls; `save_every`, checkpointing, failures and bad input behave as for unforced runs.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF, hlw_problem

INERTIA = jnp.array([2.0, 1.0, 2.0 / 3.0])
RHO = jnp.array([0.3, -0.2, 0.5])
M0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
ORDER_TOLERANCE = 0.1
# The gradient of a smooth loss against central differences with step 1e-5 (truncation
# O(1e-10), round-off O(1e-11) relative).
GRADIENT_RTOL = 1e-6


def g0_tilted():
    return lievi.SO3.exp(jnp.array([0.4, -0.3, 0.2]))


def spatial(g, m):
    """Spatial angular momentum `g Π` (and impulses `g f`) of a rigid body, batched."""
    return jnp.einsum("...ij,...j->...i", g, m)


def mixed_law(t, g, m, args):
    """Damping, a time-varying body torque and a spatially fixed torque together."""
    c, amplitude = args
    body_torque = amplitude * jnp.stack([jnp.sin(2 * t), jnp.cos(t), 0.5 + 0 * t])
    return -c * m / INERTIA + body_torque + g.T @ jnp.array([0.0, 0.0, 0.2])


KICK_INTEGRATORS = (
    lievi.DEP(chart="exp"),
    lievi.DEP(chart="cayley"),
    lievi.MoserVeselov(),
    lievi.LiePoissonSplitting(),
)
KICK_IDS = ("dep-exp", "dep-cayley", "moser-veselov", "splitting")
ALL_INTEGRATORS = KICK_INTEGRATORS + (lievi.RK4(), lievi.Composition(lievi.DEP(), 4))
ALL_IDS = KICK_IDS + ("rk4", "composition")


def first_in_default_suite(integrators, ids, default=("dep-exp",), marks=()):
    """Parameters for `parametrize`: the ones in `default` are not slow (they carry `marks`:
    `pytest.mark.extended` where even they take long), the rest are slow (each integrator
    costs a compilation; the default suite must stay fast)."""
    return [
        pytest.param(i, id=name, marks=marks if name in default else pytest.mark.slow)
        for i, name in zip(integrators, ids)
    ]


# The marks of each integrator's case without and with the potential: RK4 on the heavy top
# stays in the default suite, the other cases of DEP(exp), splitting and RK4 are extended
# (9–13 s each), the other integrators are slow.
_E, _S = pytest.mark.extended, pytest.mark.slow
ZERO_FORCING_MARKS = {
    "dep-exp": (_E, _E),
    "dep-cayley": (_S, _S),
    "moser-veselov": (_S, _S),
    "splitting": (_E, _E),
    "rk4": (_E, ()),
    "composition": (_S, _S),
}


@pytest.mark.parametrize(
    "with_potential, integrator",
    [
        pytest.param(with_potential, i, id=f"{where}-{name}", marks=ZERO_FORCING_MARKS[name][k])
        for i, name in zip(ALL_INTEGRATORS, ALL_IDS)
        for k, (with_potential, where) in enumerate([(False, "free"), (True, "heavy-top")])
    ],
)
def test_zero_forcing_is_the_unforced_run(integrator, with_potential):
    system = lievi.heavy_top(INERTIA, 1.0, RHO, 1.0) if with_potential else lievi.RigidBody(INERTIA)
    g0, n = g0_tilted(), 40
    free = lievi.simulate(system, integrator, g0, M0, h=0.1, n_steps=n)
    zero_control = lievi.simulate(
        system, integrator, g0, M0, h=0.1, n_steps=n, forcing=lievi.Control(jnp.zeros((n, 3)))
    )
    zero_law = lievi.simulate(
        system,
        integrator,
        g0,
        M0,
        h=0.1,
        n_steps=n,
        forcing=lievi.ForceLaw(lambda t, g, m, a: 0 * m),
    )
    for forced in (zero_control, zero_law):
        assert float(jnp.max(jnp.abs(forced.m - free.m))) <= 1e-14
        assert float(jnp.max(jnp.abs(forced.g - free.g))) <= 1e-14


def observed_order(system, integrator, hs, T, forcing, args):
    g0 = g0_tilted()
    g_ref, m_ref = lievi.reference_solution(system, g0, M0, [0.0, T], forcing=forcing, args=args)
    errors = []
    for h in hs:
        sol = lievi.simulate(
            system, integrator, g0, M0, h=h, n_steps=int(round(T / h)), forcing=forcing, args=args
        )
        errors.append(max(np.abs(sol.m[-1] - m_ref[-1]).max(), np.abs(sol.g[-1] - g_ref[-1]).max()))
    return np.polyfit(np.log(hs), np.log(errors), 1)[0]


@pytest.mark.parametrize(
    "integrator, order",
    [
        pytest.param(lievi.DEP(chart="exp"), 2, marks=pytest.mark.extended),  # 12 s
        pytest.param(lievi.DEP(chart="cayley"), 2, marks=pytest.mark.slow),
        pytest.param(lievi.MoserVeselov(), 2, marks=pytest.mark.slow),
        pytest.param(lievi.LiePoissonSplitting(), 2, marks=pytest.mark.slow),
        pytest.param(lievi.RK4(), 4, marks=pytest.mark.extended),  # 11 s
        pytest.param(lievi.Composition(lievi.DEP(), 4), 4, marks=pytest.mark.slow),
    ],
    ids=ALL_IDS,
)
def test_order_with_a_force_law_and_a_potential(integrator, order):
    """Heavy top + damping + time-varying torques, against DOP853 with the same forces."""
    top = lievi.heavy_top(INERTIA, 1.0, RHO, 1.0)
    p = observed_order(
        top, integrator, [0.1, 0.05, 0.025], 2.0, lievi.ForceLaw(mixed_law), (0.3, 0.5)
    )
    assert abs(p - order) < ORDER_TOLERANCE, p


@pytest.mark.extended  # 12 s
def test_order_with_a_held_control():
    """A zero-order-hold control: the reference holds `u_k` on each step, DEP is order 2."""
    body, g0, T = lievi.RigidBody(INERTIA), g0_tilted(), 1.0
    hs, errors = [0.1, 0.05, 0.025], []
    for h in hs:
        n = int(round(T / h))
        ts = h * np.arange(n + 1)
        mid = ts[:-1] + h / 2
        u = jnp.asarray(np.stack([np.sin(3 * mid), np.cos(mid), 0.3 + 0 * mid], -1))
        g_ref, m_ref = lievi.reference_solution(body, g0, M0, ts, forcing=lievi.Control(u))
        sol = lievi.simulate(body, lievi.DEP(), g0, M0, h=h, n_steps=n, forcing=lievi.Control(u))
        errors.append(max(np.abs(sol.m - m_ref).max(), np.abs(sol.g - g_ref).max()))
    p = np.polyfit(np.log(hs), np.log(errors), 1)[0]
    assert abs(p - 2) < ORDER_TOLERANCE, (p, errors)


@pytest.mark.parametrize(
    "integrator",
    first_in_default_suite(KICK_INTEGRATORS, KICK_IDS, marks=pytest.mark.extended),  # 9 s
)
def test_forced_discrete_noether_per_step(integrator):
    """`g_{k+1}Π_{k+1} − g_kΠ_k = g_k f_k⁻ + g_{k+1} f_k⁺`, every step, to round-off."""
    body, g0, h, n = lievi.RigidBody(INERTIA), g0_tilted(), 0.1, 100
    u = jnp.asarray(np.random.default_rng(0).normal(size=(n, 3)))
    sol = lievi.simulate(body, integrator, g0, M0, h=h, n_steps=n, forcing=lievi.Control(u))
    mu = spatial(sol.g, sol.m)
    impulse = h / 2 * (spatial(sol.g[:-1], u) + spatial(sol.g[1:], u))
    assert float(jnp.max(jnp.abs(mu[1:] - mu[:-1] - impulse))) <= ROUNDOFF

    # A momentum-dependent law: f_k⁺ is evaluated at the end state (the implicit kick).
    law, args = lievi.ForceLaw(mixed_law), (0.4, 0.5)
    sol = lievi.simulate(body, integrator, g0, M0, h=h, n_steps=n, forcing=law, args=args)
    f = jax.vmap(mixed_law, (0, 0, 0, None))(sol.ts, sol.g, sol.m, args)
    mu = spatial(sol.g, sol.m)
    impulse = h / 2 * (spatial(sol.g[:-1], f[:-1]) + spatial(sol.g[1:], f[1:]))
    assert float(jnp.max(jnp.abs(mu[1:] - mu[:-1] - impulse))) <= ROUNDOFF


@pytest.mark.parametrize("integrator", first_in_default_suite(KICK_INTEGRATORS, KICK_IDS))
def test_torque_about_a_fixed_axis_keeps_the_other_components(integrator):
    """A spatial torque along e₃ changes only the third component of `gΠ`."""
    body, g0 = lievi.RigidBody(INERTIA), g0_tilted()

    def law(t, g, m, args):
        return g.T @ jnp.array([0.0, 0.0, jnp.sin(t)])  # body frame of a spatial e₃ torque

    sol = lievi.simulate(body, integrator, g0, M0, h=0.1, n_steps=200, forcing=lievi.ForceLaw(law))
    mu = spatial(sol.g, sol.m)
    assert float(jnp.max(jnp.abs(mu[:, :2] - mu[0, :2]))) <= ROUNDOFF
    assert float(jnp.ptp(mu[:, 2])) > 1.0  # the torque does act


@pytest.mark.parametrize(
    "integrator",
    first_in_default_suite(KICK_INTEGRATORS[:3], KICK_IDS[:3], marks=pytest.mark.extended),  # 10 s
)
def test_damping_decays_to_rest_with_the_work_balance(integrator):
    """`u = −cΩ`: energy never increases, reaches rest, and ΔE = Σ work at O(h²)."""
    body, g0, c, T = lievi.RigidBody(INERTIA), g0_tilted(), 0.2, 40.0
    _, m_ref = lievi.reference_solution(
        body, g0, M0, [0.0, T], forcing=lievi.ForceLaw(lambda t, g, m, c: -c * m / INERTIA), args=c
    )
    E_ref = float(body.energy(jnp.asarray(m_ref[-1])))
    imbalance, final_error = [], []
    for h in (0.1, 0.05):
        sol = lievi.simulate(
            body,
            integrator,
            g0,
            M0,
            h=h,
            n_steps=int(round(T / h)),
            forcing=lievi.ForceLaw(lambda t, g, m, c: -c * m / INERTIA),
            args=c,
        )
        E = jax.vmap(body.energy)(sol.m)
        Omega = sol.m / INERTIA
        # The work of the discrete forces: f_k⁻ against Ω_k, f_k⁺ against Ω_{k+1}.
        work = h / 2 * (jnp.sum(-c * Omega[:-1] ** 2, -1) + jnp.sum(-c * Omega[1:] ** 2, -1))
        # No increase at all here (beyond round-off), well inside the method's bounded
        # O(h²) oscillation of the free body's energy.
        assert float(jnp.max(E - jax.lax.cummin(E))) <= 1e-15
        assert float(E[-1]) < 1e-6 * float(E[0])  # at rest
        imbalance.append(
            float(jnp.max(jnp.abs(E - E[0] - jnp.concatenate([jnp.zeros(1), jnp.cumsum(work)]))))
        )
        final_error.append(abs(float(E[-1]) - E_ref))
    assert 3.6 < imbalance[0] / imbalance[1] < 4.4, imbalance  # O(h²)
    assert imbalance[1] < 1e-4 * float(E[0])
    assert 3.6 < final_error[0] / final_error[1] < 4.4, final_error


def _control_loss(body, integrator, n, h):
    g_target = lievi.SO3.exp(jnp.array([0.3, 0.2, -0.4]))

    def loss(u):
        sol = lievi.simulate(
            body,
            integrator,
            jnp.eye(3),
            M0,
            h=h,
            n_steps=n,
            forcing=lievi.Control(u),
            checkpoint=True,
        )
        return jnp.sum((sol.g[-1] - g_target) ** 2) + jnp.sum(sol.m[-1] ** 2) + 1e-3 * jnp.sum(u**2)

    return loss


@pytest.mark.parametrize(
    "integrator",
    first_in_default_suite(
        [lievi.DEP(), lievi.MoserVeselov()],
        ["dep-exp", "moser-veselov"],
        marks=pytest.mark.extended,
    ),  # 18 s
)
def test_gradient_of_a_whole_control_sequence(integrator):
    """500 × 3 controls: `jax.grad` (checkpointed) against central differences."""
    body, n, h = lievi.RigidBody(INERTIA), 500, 0.01
    loss = jax.jit(_control_loss(body, integrator, n, h))
    rng = np.random.default_rng(1)
    u = jnp.asarray(0.3 * rng.normal(size=(n, 3)))
    grad = jax.jit(jax.grad(loss))(u)
    eps = 1e-5
    for _ in range(3):
        v = jnp.asarray(rng.normal(size=(n, 3)))
        v = v / jnp.linalg.norm(v)
        fd = (loss(u + eps * v) - loss(u - eps * v)) / (2 * eps)
        exact = jnp.vdot(grad, v)
        assert abs(float(fd - exact)) <= GRADIENT_RTOL * float(jnp.linalg.norm(grad)), (fd, exact)


@pytest.mark.slow
def test_jacfwd_equals_jacrev_for_controls_and_law_parameters():
    body, n, h = lievi.RigidBody(INERTIA), 20, 0.1
    rng = np.random.default_rng(2)
    u = jnp.asarray(0.3 * rng.normal(size=(n, 3)))

    def final_state(u, args):
        sol = lievi.simulate(
            body,
            lievi.DEP(),
            g0_tilted(),
            M0,
            h=h,
            n_steps=n,
            save=lievi.Save(every=n),
            forcing=(lievi.Control(u), lievi.ForceLaw(mixed_law)),
            args=args,
        )
        return jnp.concatenate([sol.m[-1], sol.g[-1].reshape(-1)])

    args = (jnp.asarray(0.3), jnp.asarray(0.5))
    forward = jax.jacfwd(final_state, argnums=(0, 1))(u, args)
    reverse = jax.jacrev(final_state, argnums=(0, 1))(u, args)
    for a, b in zip(jax.tree.leaves(forward), jax.tree.leaves(reverse)):
        assert float(jnp.max(jnp.abs(a - b))) <= ROUNDOFF
    # The damping coefficient against central differences.
    eps = 1e-6
    fd = (final_state(u, (0.3 + eps, 0.5)) - final_state(u, (0.3 - eps, 0.5))) / (2 * eps)
    assert float(jnp.max(jnp.abs(fd - forward[1][0]))) <= GRADIENT_RTOL * float(
        jnp.max(jnp.abs(fd))
    )


@pytest.mark.slow
def test_checkpoint_and_save_every_give_the_same_run():
    body, n, h = lievi.RigidBody(INERTIA), 60, 0.05
    u = jnp.asarray(np.random.default_rng(3).normal(size=(n, 3)))
    run = lambda **kw: lievi.simulate(
        body, lievi.DEP(), g0_tilted(), M0, h=h, n_steps=n, forcing=lievi.Control(u), t0=1.0, **kw
    )
    every = run()
    sparse = run(save=lievi.Save(every=6), checkpoint=True)
    assert float(jnp.max(jnp.abs(sparse.m - every.m[::6]))) == 0.0
    assert float(jnp.max(jnp.abs(sparse.ts - every.ts[::6]))) <= 1e-14

    def loss(u, **kw):
        sol = lievi.simulate(
            body, lievi.DEP(), g0_tilted(), M0, h=h, n_steps=n, forcing=lievi.Control(u), **kw
        )
        return jnp.sum(sol.m[-1] ** 2)

    plain = jax.grad(loss)(u)
    checkpointed = jax.grad(lambda u: loss(u, save=lievi.Save(every=6), checkpoint=2))(u)
    assert float(jnp.max(jnp.abs(plain - checkpointed))) <= ROUNDOFF


def test_time_reaches_the_force_law():
    """`t_k = t0 + k h` at the start of each step: a pure time signal is integrated exactly."""
    body, n, h, t0 = lievi.RigidBody(jnp.array([1.0, 1.0, 1.0])), 50, 0.1, 2.0

    def law(t, g, m, args):
        return g.T @ jnp.array([0.0, 0.0, t])  # spatial torque t e₃ on a sphere at rest

    sol = lievi.simulate(
        body,
        lievi.DEP(),
        jnp.eye(3),
        jnp.zeros(3),
        h=h,
        n_steps=n,
        t0=t0,
        forcing=lievi.ForceLaw(law),
    )
    mu3 = spatial(sol.g, sol.m)[:, 2]
    # The trapezoidal rule is exact for a linear torque: μ₃(t) = (t² − t0²)/2.
    assert float(jnp.max(jnp.abs(mu3 - (sol.ts**2 - t0**2) / 2))) <= ROUNDOFF


@pytest.mark.extended  # 8 s
def test_batch_with_per_body_controls():
    body, integrator, n, h = lievi.RigidBody(INERTIA), lievi.DEP(), 20, 0.1
    rng = np.random.default_rng(4)
    B = 3
    u = jnp.asarray(rng.normal(size=(B, n, 3)))
    g0 = jnp.stack([lievi.SO3.exp(jnp.asarray(rng.normal(size=3))) for _ in range(B)])
    m0 = jnp.asarray(rng.normal(size=(B, 3)))
    batch = lievi.simulate_batch(
        body, integrator, g0, m0, h=h, n_steps=n, save=lievi.Save(every=1), forcing=lievi.Control(u)
    )
    for b in range(B):
        one = lievi.simulate(
            body, integrator, g0[b], m0[b], h=h, n_steps=n, forcing=lievi.Control(u[b])
        )
        assert float(jnp.max(jnp.abs(batch.m[b] - one.m))) <= ROUNDOFF
    # A shared force law with args.
    batch = lievi.simulate_batch(
        body,
        integrator,
        g0,
        m0,
        h=h,
        n_steps=n,
        forcing=lievi.ForceLaw(mixed_law),
        args=(0.3, 0.5),
        save=lievi.Save(every=n),
    )
    one = lievi.simulate(
        body,
        integrator,
        g0[1],
        m0[1],
        h=h,
        n_steps=n,
        forcing=lievi.ForceLaw(mixed_law),
        args=(0.3, 0.5),
    )
    assert float(jnp.max(jnp.abs(batch.m[1, -1] - one.m[-1]))) <= ROUNDOFF
    with pytest.raises(ValueError, match="forcing"):
        lievi.simulate_batch(
            body,
            integrator,
            g0,
            m0,
            h=h,
            n_steps=n,
            forcing=lievi.Control(u[:2]),
            save=lievi.Save(every=n),
        )


@pytest.mark.slow
def test_forced_noether_on_son():
    """On SO(4) (generalized rigid body, left-invariant) the impulse law holds in Ad*."""
    rng = np.random.default_rng(5)
    body = lievi.GeneralizedRigidBody(jnp.asarray(rng.uniform(0.5, 2.0, size=4)))
    group, h, n = body.group, 0.05, 30
    g0 = group.exp(jnp.asarray(0.3 * rng.normal(size=6)))
    m0 = jnp.asarray(rng.normal(size=6))
    u = jnp.asarray(rng.normal(size=(n, 6)))
    sol = lievi.simulate(body, lievi.DEP(), g0, m0, h=h, n_steps=n, forcing=lievi.Control(u))

    def to_spatial(g, m):  # Ad*_{g⁻¹} m
        return group.Ad(group.inverse(g)).T @ m

    mu = jax.vmap(to_spatial)(sol.g, sol.m)
    impulse = h / 2 * (jax.vmap(to_spatial)(sol.g[:-1], u) + jax.vmap(to_spatial)(sol.g[1:], u))
    assert float(jnp.max(jnp.abs(mu[1:] - mu[:-1] - impulse))) <= ROUNDOFF


def test_failures_are_reported_and_masked():
    """A non-finite force under jit: a result code and NaN after the failed step, as unforced."""
    body, n = lievi.RigidBody(INERTIA), 20

    def law(t, g, m, args):
        return jnp.where(t > 0.95, jnp.nan, 0.0) * m

    sol = lievi.simulate(
        body,
        lievi.DEP(),
        jnp.eye(3),
        M0,
        h=0.1,
        n_steps=n,
        forcing=lievi.ForceLaw(law),
        throw=False,
    )
    assert int(sol.result) != int(lievi.RESULTS.successful)
    k = int(sol.stats["failed_step"])
    assert 8 <= k <= 10
    assert bool(jnp.all(jnp.isfinite(sol.m[: k + 1]))) and bool(jnp.all(jnp.isnan(sol.m[k + 1 :])))
    with pytest.raises(Exception, match="step failed"):
        lievi.simulate(
            body, lievi.DEP(), jnp.eye(3), M0, h=0.1, n_steps=n, forcing=lievi.ForceLaw(law)
        )
    # Non-finite controls only known under jit: reported, not silent.
    u = jnp.zeros((n, 3)).at[5].set(jnp.inf)
    run = jax.jit(
        lambda u: lievi.simulate(
            body,
            lievi.DEP(),
            jnp.eye(3),
            M0,
            h=0.1,
            n_steps=n,
            forcing=lievi.Control(u),
            throw=False,
        )
    )
    sol = run(u)
    assert int(sol.result) != int(lievi.RESULTS.successful) and int(sol.stats["failed_step"]) == 5


def test_bad_input():
    body, n = lievi.RigidBody(INERTIA), 10
    run = lambda forcing, **kw: lievi.simulate(
        body, lievi.DEP(), jnp.eye(3), M0, h=0.1, n_steps=n, forcing=forcing, **kw
    )
    with pytest.raises(ValueError, match=r"`forcing`.*\(10, 3\)"):
        run(lievi.Control(jnp.zeros((n, 2))))
    with pytest.raises(ValueError, match=r"`forcing`.*\(10, 3\)"):
        run(lievi.Control(jnp.zeros((n + 1, 3))))
    with pytest.raises(ValueError, match=r"`forcing`.*NaN or inf.*step 4"):
        run(lievi.Control(jnp.zeros((n, 3)).at[4, 1].set(jnp.nan)))
    with pytest.raises(ValueError, match=r"`forcing`.*shape \(3,\)"):
        run(lievi.ForceLaw(lambda t, g, m, args: jnp.zeros(2)))
    with pytest.raises(ValueError, match=r"`forcing`.*could not be evaluated"):
        run(lievi.ForceLaw(lambda t, g: g))
    with pytest.raises(ValueError, match=r"`forcing`.*lievi.Control\(u\)"):
        run(jnp.zeros((n, 3)))
    with pytest.raises(ValueError, match="g1"):
        lievi.simulate(
            body,
            lievi.DEP(),
            jnp.eye(3),
            g1=lievi.SO3.exp(jnp.array([0.1, 0, 0])),
            h=0.1,
            n_steps=n,
            forcing=lievi.Control(jnp.zeros((n, 3))),
        )
    with pytest.raises(ValueError, match="forcing"):
        body_hlw, g0, m0 = hlw_problem()
        lievi.simulate(
            body_hlw,
            lievi.PreprocessedMoserVeselov(4),
            g0,
            m0,
            h=0.1,
            n_steps=n,
            forcing=lievi.Control(jnp.zeros((n, 3))),
        )


@pytest.mark.extended  # 13 s
def test_float32_forced_run():
    body = lievi.RigidBody(INERTIA.astype(jnp.float32))
    n = 50
    u = jnp.asarray(np.random.default_rng(6).normal(size=(n, 3)), jnp.float32)
    sol = lievi.simulate(
        body,
        lievi.DEP(),
        jnp.eye(3, dtype=jnp.float32),
        M0.astype(jnp.float32),
        h=jnp.float32(0.1),
        n_steps=n,
        forcing=lievi.Control(u),
    )
    ref = lievi.simulate(
        body,
        lievi.DEP(),
        jnp.eye(3),
        M0,
        h=0.1,
        n_steps=n,
        forcing=lievi.Control(u.astype(jnp.float64)),
    )
    assert sol.m.dtype == jnp.float32
    assert float(jnp.max(jnp.abs(sol.m - ref.m))) <= 1e-4
    # A float64 constant inside a force law does not promote the float32 run.
    law = lievi.ForceLaw(lambda t, g, m, c: -c * m / INERTIA)
    sol = lievi.simulate(
        body,
        lievi.DEP(),
        jnp.eye(3, dtype=jnp.float32),
        M0.astype(jnp.float32),
        h=jnp.float32(0.1),
        n_steps=n,
        forcing=law,
        args=0.2,
    )
    assert sol.m.dtype == jnp.float32 and int(sol.result) == int(lievi.RESULTS.successful)


def test_control_accepts_array_likes():
    """`Control` converts its argument with `jnp.asarray`: nested lists and tuples, NumPy
    arrays and integers give the same run as the JAX float array, bit for bit."""
    body, n = lievi.RigidBody(INERTIA), 6
    u = np.random.default_rng(7).normal(size=(n, 3))
    run = lambda control: lievi.simulate(
        body, lievi.DEP(), jnp.eye(3), M0, h=0.1, n_steps=n, forcing=control
    )
    expected = run(lievi.Control(jnp.asarray(u)))
    for like in [u.tolist(), tuple(map(tuple, u.tolist())), u]:
        control = lievi.Control(like)
        assert isinstance(control.u, jax.Array) and control.u.shape == (n, 3)
        sol = run(control)
        np.testing.assert_array_equal(sol.m, expected.m)
        np.testing.assert_array_equal(sol.g, expected.g)
    # The case that used to fail deep inside the scan: a nested list of zeros.
    zeros = run(lievi.Control([[0.0, 0.0, 0.0]] * n))
    np.testing.assert_array_equal(zeros.m, run(lievi.Control(jnp.zeros((n, 3)))).m)
    integers = lievi.Control([[1, 0, 0]] * n)
    assert jnp.issubdtype(integers.u.dtype, jnp.floating)
    np.testing.assert_array_equal(
        run(integers).m, run(lievi.Control(jnp.tile(jnp.array([1.0, 0.0, 0.0]), (n, 1)))).m
    )


@pytest.mark.parametrize(
    "u",
    [
        pytest.param(jnp.zeros(3), id="one-step"),
        pytest.param(0.0, id="scalar"),
        pytest.param(jnp.zeros((4, 0)), id="d=0"),
        pytest.param([[0.0, 0.0, 0.0], [0.0, 0.0]], id="ragged"),
        pytest.param(jnp.zeros((4, 3), jnp.complex64), id="complex"),
        pytest.param(np.zeros((4, 3), bool), id="bool"),
        pytest.param("0, 0, 0", id="string"),
        pytest.param(None, id="none"),
        pytest.param([[object()] * 3] * 4, id="objects"),
    ],
)
def test_control_rejects_non_arrays(u):
    """Anything but a real array of shape (n_steps, d) (or (batch, n_steps, d)) is a
    `ValueError` at construction, naming the argument and the fix."""
    with pytest.raises(ValueError, match=r"`u` of lievi.Control.*shape \(n_steps, d\)"):
        lievi.Control(u)


def test_control_with_axes_the_system_does_not_have():
    """A control with more axes than one run of the system has (one body, `(n_steps, 3)`)
    is accepted at construction (a system of N bodies takes `(n_steps, N, 6)`) and
    rejected by the run, naming the shape it needs; in a batch, one extra leading axis is
    the batch."""
    system = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
    u = lievi.Control(jnp.zeros((2, 4, 4, 3)))
    with pytest.raises(ValueError, match=r"must have shape \(4, 3\)"):
        lievi.simulate(system, lievi.DEP(), jnp.eye(3), jnp.ones(3), h=0.1, n_steps=4, forcing=u)
    with pytest.raises(ValueError, match=r"must have shape \(4, 3\)"):
        lievi.simulate_batch(
            system,
            lievi.DEP(),
            jnp.eye(3),
            jnp.ones((2, 3)),
            h=0.1,
            n_steps=4,
            forcing=u,
            save=lievi.Save(every=4),
        )
