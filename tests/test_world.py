"""`lievi.state_from_world` / `lievi.state_to_world`: world positions, velocities,
attitudes and angular velocities to lievi's `(g, m)` and back.

Decided by a case computed by hand (a quarter turn about z: `Π = J Rᵀω`, `P = m Rᵀṗ`), by
round trips (a generic batch, several bodies, a Kirchhoff tensor with off-diagonal
blocks), and by the library's own spatial momentum, whose linear part must be `m ṗ` and
angular part `J_world ω + p × m ṗ` for a body in vacuum. Float64.
"""

import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import ROUNDOFF
from lievi import diagnostics as dg

SO3 = lievi.SO3


def test_quarter_turn_by_hand():
    body = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    R = jnp.array([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]])  # +90° about z
    p, p_dot = jnp.array([1.0, 2.0, 3.0]), jnp.array([1.0, 0.0, 0.0])
    omega = jnp.array([0.5, 0.0, 1.5])  # world
    g, m = lievi.state_from_world(body, p, p_dot, R, omega)
    # Ω = Rᵀω = (0, −0.5, 1.5), Π = JΩ = (0, −1, 4.5); v = Rᵀṗ = (0, −1, 0), P = 2v.
    np.testing.assert_allclose(m, [0.0, -1.0, 4.5, 0.0, -2.0, 0.0], rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(g[:3, :3], R, rtol=0, atol=0)
    np.testing.assert_allclose(g[:3, 3], p, rtol=0, atol=0)
    np.testing.assert_allclose(g[3], [0.0, 0.0, 0.0, 1.0], rtol=0, atol=0)


def _random_world(rng, shape):
    return (
        jnp.asarray(rng.normal(size=shape + (3,))),
        jnp.asarray(rng.normal(size=shape + (3,))),
        SO3.exp(jnp.asarray(rng.normal(size=shape + (3,)))),
        jnp.asarray(rng.normal(size=shape + (3,))),
    )


@pytest.mark.parametrize("kind", ["bodies", "kirchhoff"])
def test_round_trip_and_spatial_momentum(kind):
    rng = np.random.default_rng(0)
    if kind == "bodies":  # a batch of 4 states of 3 bodies
        inertia = jnp.asarray(rng.uniform(1.0, 2.0, size=(3, 3)))
        mass = jnp.array([1.0, 2.0, 0.5])
        system, shape = lievi.RigidBodies(inertia, mass), (4, 3)
    else:  # one body in a fluid: a full SPD tensor, origin off the centre of mass
        A = rng.normal(size=(6, 6))
        system, shape = lievi.RigidBodySE3(tensor=jnp.asarray(A @ A.T + 6 * np.eye(6))), (5,)
    world = _random_world(rng, shape)
    g, m = lievi.state_from_world(system, *world)
    assert g.shape == shape + (4, 4) and m.shape == shape + (6,)
    back = lievi.state_to_world(system, g, m)
    assert isinstance(back, lievi.WorldState)
    for name, x, y in zip(back._fields, back, world):
        np.testing.assert_allclose(x, y, rtol=0, atol=ROUNDOFF, err_msg=name)
    # lievi's kinetic energy of (g, m) is the world one, ½ωᵀ(R J Rᵀ)ω + ½ m|ṗ|² in vacuum.
    if kind == "bodies":
        p, p_dot, R, omega = world
        J_world = R @ (inertia[..., None] * jnp.eye(3)) @ jnp.swapaxes(R, -1, -2)
        expected = 0.5 * jnp.einsum("...i,...ij,...j->...", omega, J_world, omega)
        expected = jnp.sum(expected + 0.5 * mass * jnp.sum(p_dot**2, -1), axis=-1)
        np.testing.assert_allclose(dg.energy(system, g, m), expected, rtol=ROUNDOFF)
        # The spatial momentum: linear m ṗ, angular J_world ω + p × m ṗ.
        spatial = dg.spatial_momentum(system, g, m)
        linear = mass[:, None] * p_dot
        angular = jnp.einsum("...ij,...j->...i", J_world, omega) + jnp.cross(p, linear)
        np.testing.assert_allclose(spatial[..., 3:], linear, rtol=0, atol=ROUNDOFF)
        np.testing.assert_allclose(spatial[..., :3], angular, rtol=0, atol=ROUNDOFF)


def test_bad_input():
    body = lievi.RigidBodySE3(jnp.ones(3), 1.0)
    p, v, R, w = jnp.zeros(3), jnp.zeros(3), jnp.eye(3), jnp.zeros(3)
    with pytest.raises(ValueError, match="`attitudes` must have shape"):
        lievi.state_from_world(body, p, v, jnp.eye(4), w)
    with pytest.raises(ValueError, match="`attitudes` must be rotation matrices"):
        lievi.state_from_world(body, p, v, 2 * R, w)
    with pytest.raises(ValueError, match="`velocities` has leading axes"):
        lievi.state_from_world(body, p, jnp.zeros((2, 3)), R, w)
    with pytest.raises(ValueError, match="rigid body on SE\\(3\\)"):
        lievi.state_from_world(lievi.RigidBody(jnp.ones(3)), p, v, R, w)
    with pytest.raises(ValueError, match=r"`g` must have shape \(\*batch, 2, 4, 4\)"):
        lievi.state_to_world(
            lievi.RigidBodies(jnp.ones((2, 3)), jnp.ones(2)), jnp.eye(4), jnp.zeros(6)
        )
