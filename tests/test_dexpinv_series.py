"""`MatrixLieGroup.dexpinv_series`: `dexpinv`'s commutator series truncated after
`ad_x^degree` (the Lie-group Runge–Kutta methods' `dexp⁻¹`, docs/theory/closed-forms.md).
The SO(3) and SE(3) closed forms against the generic Bernoulli series on `ad_x`, and the
truncation error's order against the exact `dexpinv`."""

from __future__ import annotations

import numpy as np
import pytest

import lievi
from lievi._groups._base import MatrixLieGroup

GROUPS = {"so3": (lievi.SO3, 3), "se3": (lievi.SE3, 6)}


@pytest.mark.parametrize("name", GROUPS)
@pytest.mark.parametrize("degree", [0, 1, 4, 8])
def test_closed_form_matches_the_bernoulli_series(name, degree):
    """The closed form (`I − x̂/2 + c(θ²) x̂²`, `c` a polynomial) is the series itself, at
    angles up to the methods' chart bound 3."""
    group, d = GROUPS[name]
    x = np.random.default_rng(degree).normal(size=(5, d))
    x *= np.linspace(0.0, 3.0, 5)[:, None] / np.linalg.norm(x[:, :3], axis=1, keepdims=True)
    generic = MatrixLieGroup.dexpinv_series(group, x, degree)
    np.testing.assert_allclose(group.dexpinv_series(x, degree), generic, rtol=0, atol=1e-13)


@pytest.mark.parametrize("name", GROUPS)
def test_truncation_error_has_the_next_order(name):
    """Truncated after `ad_x⁷` the series misses `B_8/8! ad_x⁸ + …`: halving `x` divides the
    error by `2⁸`; with 30 terms it is `dexpinv` to round-off at `|x| = 1`."""
    group, d = GROUPS[name]
    x = np.random.default_rng(1).normal(size=d)
    x /= np.linalg.norm(x)
    np.testing.assert_allclose(group.dexpinv_series(x, 30), group.dexpinv(x), rtol=0, atol=1e-14)
    errors = [
        np.abs(group.dexpinv_series(s * x, 7) - group.dexpinv(s * x)).max() for s in (0.4, 0.2)
    ]
    assert 2**8 * 0.9 < errors[0] / errors[1] < 2**8 * 1.1


@pytest.mark.parametrize("degree", [-1, 2.0, True])
def test_bad_degree_is_named(degree):
    with pytest.raises(ValueError, match="`degree` must be an integer"):
        lievi.SO3.dexpinv_series(np.zeros(3), degree)
