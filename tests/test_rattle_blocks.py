"""RATTLE's closed-form momentum blocks against `jax.jacfwd` of the momentum term."""

import jax
import jax.numpy as jnp
import pytest

from lievi._groups._charts import as_chart
from lievi._groups._se3 import SE3
from lievi._integrators._rattle_blocks import momentum_blocks


@pytest.mark.parametrize("chart, order, bound", [("exp", 4, 1e-8), ("cayley", 2, 1e-3)])
def test_momentum_blocks_match_jacfwd_to_their_order(chart, order, bound):
    """The error relative to `M/h` falls as `|ξ|^order` (exp: its ad³ term vanishes)."""
    chart = as_chart(chart)
    key = jax.random.PRNGKey(3)
    L = jax.random.normal(key, (3, 6, 6))
    tensor = L @ jnp.swapaxes(L, 1, 2) + 6 * jnp.eye(6)
    direction = jax.random.normal(jax.random.fold_in(key, 1), (3, 6))
    h = 0.01

    def error(size):
        xi = size * direction
        exact = jax.vmap(jax.jacfwd(lambda x, M: chart.dinverse(SE3, x).T @ (M @ x) / h))(
            xi, tensor
        )
        approx = momentum_blocks(xi, tensor, h, chart.ad_squared)
        return float(jnp.max(jnp.abs(exact - approx)) / jnp.max(jnp.abs(tensor / h)))

    big, small = error(1e-1), error(1e-2)
    assert small < bound  # at |ξ| ≈ 0.02
    assert big / small == pytest.approx(10.0**order, rel=0.2)
