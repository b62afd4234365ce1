"""Learned dynamics: `lievi.NeuralPotential` inside the variational integrator.

Default suite: a neural potential is a potential like any other (the symmetry it is given
is kept to round-off, gradients reach its weights, bad input is refused). Slow: trained on
noisy heavy-top data against a diffrax neural ODE with the same data and budget, the
variational model's held-out torque error is small and its energy error stays bounded over
10× the training horizon where the neural ODE's drifts (`notebooks/06_learned_dynamics`
shows the same at full size).
"""

import diffrax
import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

import lievi
from helpers import ROUNDOFF

INERTIA = jnp.array([1.0, 1.2, 0.6])
H = 0.05


@pytest.mark.extended  # 16 s
def test_neural_potential_keeps_its_symmetry_and_is_differentiable():
    """With `features="vertical"` V depends on Γ = gᵀe₃ only: `e₃·(gΠ)` is conserved."""
    potential = lievi.NeuralPotential(
        3, key=jax.random.PRNGKey(0), features="vertical", width_size=8
    )
    body = lievi.RigidBody(INERTIA, potential=potential)
    g0 = lievi.SO3.exp(jnp.array([0.5, -0.3, 0.2]))
    m0 = jnp.array([0.3, -0.5, 0.4])
    sol = lievi.simulate(body, lievi.DEP(), g0, m0, h=H, n_steps=100)
    vertical_momentum = jnp.einsum("kij,kj->ki", sol.g, sol.m)[:, 2]
    assert float(jnp.ptp(vertical_momentum)) <= ROUNDOFF
    assert float(jnp.ptp(jax.vmap(body.force)(sol.g))) > 1e-3  # the network does act

    def loss(model):
        out = lievi.simulate(model, lievi.DEP(), g0, m0, h=H, n_steps=10, save=lievi.Save(every=10))
        return jnp.sum(out.m[-1] ** 2)

    grads = eqx.filter_grad(loss)(body)
    leaves = jax.tree.leaves(eqx.filter(grads.potential, eqx.is_inexact_array))
    assert all(bool(jnp.all(jnp.isfinite(x))) for x in leaves)
    assert max(float(jnp.max(jnp.abs(x))) for x in leaves) > 0


def test_neural_potential_bad_input():
    with pytest.raises(ValueError, match="features"):
        lievi.NeuralPotential(3, key=jax.random.PRNGKey(0), features="angles")
    with pytest.raises(ValueError, match="`n`"):
        lievi.NeuralPotential(1, key=jax.random.PRNGKey(0))


@pytest.mark.slow
def test_learned_potential_against_a_neural_ode():
    true = lievi.heavy_top(INERTIA, 1.0, jnp.array([0.1, -0.1, 0.6]), gravity=1.0)
    rng = np.random.default_rng(0)
    n_train, window, noise = 60, 10, 1e-3

    def random_state():
        return lievi.SO3.exp(jnp.asarray(0.8 * rng.normal(size=3))), jnp.asarray(
            0.7 * rng.normal(size=3)
        )

    def truth(g0, m0, n):
        sol = lievi.simulate(
            true,
            lievi.Composition(lievi.DEP(), 4),
            g0,
            m0,
            h=H / 4,
            n_steps=4 * n,
            save=lievi.Save(every=4),
        )
        return sol.g, sol.m

    observed = []
    for _ in range(3):
        g, m = truth(*random_state(), n_train)
        g = jax.vmap(lambda gi, e: gi @ lievi.SO3.exp(e))(
            g, jnp.asarray(noise * rng.normal(size=(len(g), 3)))
        )
        observed.append((g, m + noise * jnp.asarray(rng.normal(size=m.shape))))
    starts = range(0, n_train - window + 1, 5)
    G0 = jnp.stack([g[k] for g, _ in observed for k in starts])
    M0 = jnp.stack([m[k] for _, m in observed for k in starts])
    GW = jnp.stack([g[k : k + window + 1] for g, _ in observed for k in starts])
    MW = jnp.stack([m[k : k + window + 1] for _, m in observed for k in starts])

    variational = lievi.RigidBody(
        INERTIA, potential=lievi.NeuralPotential(3, key=jax.random.PRNGKey(0), features="vertical")
    )

    def rollout_variational(model, g0, m0, n):
        sol = lievi.simulate(model, lievi.DEP(), g0, m0, h=H, n_steps=n, throw=False)
        return sol.g, sol.m

    class NeuralODE(eqx.Module):
        mlp: eqx.nn.MLP

        def __call__(self, t, y, args):
            return self.mlp(y)

    def rollout_ode(model, g0, m0, n):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(model),
            diffrax.Tsit5(),
            0.0,
            n * H,
            H,
            jnp.concatenate([m0, g0.reshape(-1)]),
            saveat=diffrax.SaveAt(ts=H * jnp.arange(n + 1)),
            max_steps=n,
        )
        return sol.ys[:, 3:].reshape(-1, 3, 3), sol.ys[:, :3]

    neural_ode = NeuralODE(
        eqx.nn.MLP(12, 12, 64, 2, activation=jax.nn.softplus, key=jax.random.PRNGKey(1))
    )

    def train(model, rollout, frozen=None, steps=60):
        def loss(params):
            g, m = jax.vmap(lambda g0, m0: rollout(eqx.combine(params, static), g0, m0, window))(
                G0, M0
            )
            return jnp.mean((g - GW) ** 2) + jnp.mean((m - MW) ** 2)

        params, static = eqx.partition(model, eqx.is_inexact_array)
        opt = optax.adam(3e-3)
        state = opt.init(params)

        @jax.jit
        def step(params, state):
            grad = jax.grad(loss)(params)
            if frozen is not None:
                grad = eqx.tree_at(frozen, grad, replace_fn=jnp.zeros_like)
            updates, state = opt.update(grad, state, params)
            return optax.apply_updates(params, updates), state

        for _ in range(steps):
            params, state = step(params, state)
        return eqx.combine(params, static)

    variational = train(variational, rollout_variational, frozen=lambda m: m.inertia)
    neural_ode = train(neural_ode, rollout_ode)

    g_true, m_true = truth(*random_state(), 10 * n_train)  # held out, 10× the horizon
    torque = jax.vmap(true.force)(g_true)
    learned = jax.vmap(variational.force)(g_true)
    torque_error = float(jnp.sqrt(jnp.mean((learned - torque) ** 2) / jnp.mean(torque**2)))
    assert torque_error < 0.1, torque_error

    def energy(g, m):
        return jax.vmap(lambda gi, mi: true.energy(mi) + true.potential_energy(gi))(g, m)

    E0 = energy(g_true[:1], m_true[:1])[0]
    scale = true.energy(m_true[0]) + jnp.linalg.norm(true.potential.center_of_mass)  # mγ = 1
    drift = {}
    for name, (g, m) in {
        "variational": rollout_variational(variational, g_true[0], m_true[0], 10 * n_train),
        "neural ODE": rollout_ode(neural_ode, g_true[0], m_true[0], 10 * n_train),
    }.items():
        drift[name] = float(jnp.max(jnp.abs(energy(g, m) - E0)) / scale)
    assert drift["variational"] < 0.1, drift
    assert drift["neural ODE"] > 10 * drift["variational"], drift
