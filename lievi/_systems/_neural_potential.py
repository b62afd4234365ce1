"""A learnable potential: an `eqx.nn.MLP` of the group element, for learned dynamics.

The Lagrangian `l(ξ) − V_θ(g)` with `V_θ` a neural network is still a Lagrangian: run
through a variational integrator (`lievi.DEP`) the learned model is symplectic and
momentum-preserving for every `θ`, and its energy `H(m) + V_θ(g)` stays bounded over long
horizons — the structure a black-box neural ODE has to learn and in general does not (Lee,
Leok & McClamroch's Lie group variational integrators; Duruisseaux et al., *Lie group
forced variational integrator networks*, 2023). The force is `−dV_θ` by autodiff
(`AbstractLieSystem.force`), and training differentiates through the implicit steps by the
implicit function theorem.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
from jaxtyping import Array, Float, PRNGKeyArray

from ._potential import AbstractPotential

FEATURES = ("entries", "vertical")


class NeuralPotential(AbstractPotential):
    """`V_θ(g)`: a multilayer perceptron of the entries of `g`, a learnable potential.

    Pass it as a system's potential, e.g. `lievi.RigidBody(inertia,
    potential=lievi.NeuralPotential(3, key=key))`, and fit its parameters (`eqx.filter`
    with `eqx.is_inexact_array`) to observed trajectories with optax: the loss is a
    distance between `lievi.simulate(...)` rollouts and the observations, and `jax.grad`
    goes through every step. See `docs/forcing.md` and
    `notebooks/06_learned_dynamics.ipynb`.

    **Arguments:**

    - `n`: the matrix size of the group (3 for SO(3)).
    - `key`: a `jax.random` key for the initial weights.
    - `features`: what the network sees. `"entries"` (default): all `n²` entries of `g`,
      no symmetry assumed. `"vertical"`: only the last row of `g`, the world's vertical
      `Γ = gᵀe_z` in body coordinates — the advected parameter of a body in a uniform
      field (paper §7), which builds in the symmetry about the vertical.
    - `width_size`, `depth`: of the hidden layers.
    - `activation`: a smooth activation (the force is the network's derivative, and
      training differentiates it once more); default `jax.nn.softplus`.
    - `dtype`: of the weights (default float64 when x64 is enabled, else float32).
    """

    mlp: eqx.nn.MLP
    features: str = eqx.field(static=True)

    def __init__(
        self,
        n: int,
        *,
        key: PRNGKeyArray,
        features: str = "entries",
        width_size: int = 32,
        depth: int = 2,
        activation=jax.nn.softplus,
        dtype=None,
    ):
        if features not in FEATURES:
            raise ValueError(f"`features` must be one of {FEATURES}, got {features!r}.")
        if isinstance(n, bool) or not isinstance(n, int) or n < 2:
            raise ValueError(f"`n` must be the group's matrix size, an integer ≥ 2, got {n!r}.")
        dtype = jnp.result_type(float) if dtype is None else dtype
        in_size = n * n if features == "entries" else n
        self.mlp = eqx.nn.MLP(
            in_size, "scalar", width_size, depth, activation=activation, key=key, dtype=dtype
        )
        self.features = features

    def __call__(self, g: Float[Array, "n n"]):
        x = g.reshape(-1) if self.features == "entries" else g[-1]
        return self.mlp(x.astype(self.mlp.layers[0].weight.dtype))
