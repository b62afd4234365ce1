"""The joints' block solve (`lievi._systems._tree_solve`) against a dense solve."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lievi._small_linalg import inverse
from lievi._systems._tree_solve import tree_solver, tree_structure

# (parents, joint sizes): a chain of hinges, a branching tree with a floating root and a
# mix of ball (3) and hinge (5) joints, two trees hanging from the world.
TREES = [
    ((-1, 0, 1, 2, 3), (5, 5, 5, 5, 5)),
    ((-1, 0, 0, 1, 1, 2), (0, 3, 5, 3, 3, 5)),
    ((-1, -1, 0, 1, 2), (3, 5, 3, 3, 5)),
]


def _tree_matrix(parents, sizes, key, skew):
    """`C M⁻¹ Cᵀ + skew·E` with each joint's rows of `C` on its two bodies only, `M`
    blockdiagonal SPD, `E` a random matrix with the same block pattern (RATTLE's Schur
    complement is such a perturbation of the Gram matrix)."""
    n = len(parents)
    k1, k2, k3 = jax.random.split(key, 3)
    rows = []
    for i, size in enumerate(sizes):
        if not size:
            continue
        touched = jnp.array([j in (i, parents[i]) for j in range(n)], jnp.float64)
        rows.append(jax.random.normal(jax.random.fold_in(k1, i), (size, n, 6)) * touched[:, None])
    C = jnp.concatenate(rows).reshape(-1, 6 * n)
    L = jax.random.normal(k2, (n, 6, 6))
    M_inv = jax.scipy.linalg.block_diag(*(L @ jnp.swapaxes(L, 1, 2) + 6 * jnp.eye(6)))
    gram = C @ M_inv @ C.T
    pattern = (jnp.abs(gram) > 0).astype(jnp.float64)
    return gram + skew * pattern * jax.random.normal(k3, gram.shape)


@pytest.mark.parametrize("parents, sizes", TREES)
@pytest.mark.parametrize("skew", [0.0, 0.1])
def test_tree_solver_matches_dense_solve(parents, sizes, skew):
    key = jax.random.PRNGKey(sum(sizes))
    S = _tree_matrix(parents, sizes, key, skew)
    c = S.shape[0]
    r = jax.random.normal(jax.random.fold_in(key, 7), (c,))
    expected = jnp.linalg.solve(S, r)
    got = jax.jit(lambda S, r: tree_solver(S, tree_structure(parents, sizes))(r))(S, r)
    assert np.linalg.cond(np.asarray(S)) < 1e6  # well conditioned: the bound below means it
    np.testing.assert_allclose(
        got, expected, rtol=0, atol=1e-11 * float(jnp.max(jnp.abs(expected)))
    )


def test_tree_structure_orders_leaves_first_and_pairs_joints_on_a_body():
    offsets, order, neighbours = tree_structure((-1, 0, 0, 1), (0, 3, 5, 3))
    assert [offsets[i] for i in (1, 2, 3)] == [slice(0, 3), slice(3, 8), slice(8, 11)]
    assert order[0] == 3  # the deepest joint first
    assert sorted(neighbours[1]) == [2, 3] and neighbours[3] == [1] and neighbours[2] == [1]


@pytest.mark.parametrize("n", [3, 5, 6])
def test_small_inverse_against_lapack(n):
    """`_small_linalg.inverse` (Gauss–Jordan in order, looped) on a batch of SPD blocks
    perturbed as RATTLE's are: LAPACK's inverse to 1e-13 relative, and its derivative
    (reverse mode through the loop) `−A⁻¹ dA A⁻¹`."""
    rng = np.random.default_rng(n)
    L = rng.normal(size=(4, 2, n, n))
    A = jnp.asarray(L @ np.swapaxes(L, -1, -2) + n * np.eye(n) + 0.1 * rng.normal(size=L.shape))
    inv = inverse(A)
    expected = np.linalg.inv(np.asarray(A))
    assert np.max(np.abs(inv - expected)) <= 1e-13 * np.max(np.abs(expected))
    dA = jnp.asarray(rng.normal(size=(n, n)))
    grad = jax.grad(lambda a: jnp.sum(inverse(a) * dA))(A[0, 0])
    exact = -(expected[0, 0].T @ np.asarray(dA) @ expected[0, 0].T)
    assert np.max(np.abs(grad - exact)) <= 1e-12 * np.max(np.abs(exact))
