"""SO(n), n = 2..8: coordinates, group axioms, algebra identities, log, batching.

Compiling the generic operators dominates the run time, so for each `n` every method is
evaluated once, in one jitted function on inputs of batch shape (2, 5) (stacked to
(2, 2, 5) or (3, 2, 5) where that gives more samples for free), and the tests check that
report with NumPy on the host (in float64, nothing more to compile). The same compiled
function on a batch whose elements are all equal checks that batch elements do not mix.
Derivatives are tested in `test_group_autodiff.py`.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import lievi
from helpers import ROUNDOFF, random_rotation

# SO(n) for n = 5, 6, 7 are extended: the generic operators compile once per n (6–9 s each);
# n = 2, 3, 4 and 8 stay in the default suite, the smallest cases and the largest.
NS = (2, 3, 4, *(pytest.param(n, marks=pytest.mark.extended) for n in (5, 6, 7)), 8)
BATCH = (2, 5)
# log(exp x) = x is asserted for |x| ≤ 2.5 in random directions, and for single rotation
# planes at π − 1e-7 and 3; SOn.log is meant for every angle below π.
LOG_RADIUS = 2.5
SWITCH = np.sqrt(1e-3)  # the float64 Taylor switch of the SO(3) closed forms, θ² = 1e-3
# Compilation dominates the run time of these tests. XLA's backend optimisation level 0
# halves it; floating-point semantics are the same (no fast-math at any level; results
# differ from the default level by at most an ulp or two).
FAST_COMPILE = {"xla_backend_optimization_level": 0}


def _apply(M, y):
    return np.einsum("...ab,...b->...a", M, y)


def _inner(X, Y):
    """⟨X, Y⟩ = tr(XᵀY)/2, batched."""
    return np.einsum("...ab,...ab->...", X, Y) / 2


def _hat_np(E, x):
    """x̂ = Σ x_a E_a on the host, from the library's basis."""
    return np.einsum("...a,aij->...ij", x, E)


def _vee_np(E, X):
    """Coordinates of the skew part of X in the orthonormal basis E."""
    return np.einsum("aij,...ij->...a", E, X) / 2


@functools.cache
def _inputs(n):
    """Algebra elements x, y, z and random rotations g, k, all of batch shape BATCH, and
    a random n × n matrix M.

    x and y have norms uniform in [0, LOG_RADIUS] and [0, π), z is standard normal. Part
    of x is special: x[0, 0] = 0, x[0, 1] a single plane at π − 1e-7 (nearly a
    half-turn), x[0, 2] a plane at 3.0, and in random directions x[0, 3] at 1e-9, x[0, 4]
    at 1e-4, x[1, 0] and x[1, 1] just below and above the Taylor switch θ² = 1e-3.
    """
    d = n * (n - 1) // 2
    rng = np.random.default_rng(100 + n)

    def ball(radius):
        v = rng.normal(size=BATCH + (d,))
        v /= np.linalg.norm(v, axis=-1, keepdims=True)
        return v * rng.uniform(0, radius, size=BATCH + (1,))

    x, y = ball(LOG_RADIUS), ball(np.pi)
    z = rng.normal(size=BATCH + (d,))
    special_norms = {
        (0, 3): 1e-9,
        (0, 4): 1e-4,
        (1, 0): SWITCH * (1 - 1e-12),
        (1, 1): SWITCH * (1 + 1e-12),
    }
    for index, norm in special_norms.items():
        x[index] *= norm / np.linalg.norm(x[index])
    x[0, :3] = 0.0
    x[0, 1, 0] = np.pi - 1e-7
    x[0, 2, -1] = 3.0
    count = int(np.prod(BATCH))
    g, k = (
        np.stack([random_rotation(rng, n) for _ in range(count)]).reshape(BATCH + (n, n))
        for _ in range(2)
    )
    M = rng.normal(size=(n, n))
    return x, y, z, g, k, M


def _off_group(g):
    """g with its first row stretched by 1e-3 (not orthogonal), and g with its first row
    negated (orthogonal, det = −1)."""
    return g.at[..., 0, :].multiply(1 + 1e-3), g.at[..., 0, :].multiply(-1)


def _evaluate(group, x, y, z, g, k, M):
    """Every method of `group` once, batched; identities are checked on the host.

    The chart maps see x and y stacked (batch (2, 2, 5)), `log` sees exp(x) and the
    random rotations g stacked: more samples for the same compilation.
    """
    xy = jnp.stack([x, y])
    e = group.exp(xy)
    c = group.cay(xy)
    ad_x, ad_y, ad_z = group.ad(jnp.stack([x, y, z]))
    stretched, reflected = _off_group(g)
    return dict(
        basis=group.basis(),
        hat_eye=group.hat(jnp.eye(group.algebra_dim)),
        vee_M=group.vee(M),
        hat_vee_M=group.hat(group.vee(M)),
        hat=group.hat(xy),
        vee_hat=group.vee(group.hat(xy)),
        exp=e,
        log=group.log(jnp.stack([e[0], g])),
        dexp=group.dexp(xy),
        dexpinv=group.dexpinv(xy),
        cay=c,
        cayinv_cay=group.cayinv(c),
        dcay=group.dcay(xy),
        dcayinv=group.dcayinv(xy),
        ad_x=ad_x,
        ad_y=ad_y,
        ad_z=ad_z,
        Ad=group.Ad(g),
        bracket=group.bracket(x, y),
        inverse=group.inverse(g),
        compose=group.compose(g, k),
        compose_left=group.compose(group.compose(g, k), e[0]),
        compose_right=group.compose(g, group.compose(k, e[0])),
        compose_identity=group.compose(group.identity(), g),
        defect=group.membership_defect(jnp.stack([e[0], g])),
        defect_off_group=group.membership_defect(jnp.stack([stretched, reflected])),
    )


# Outputs of _evaluate without batch axes, and with a leading stack axis of 2 before them.
UNBATCHED = {"basis", "hat_eye", "vee_M", "hat_vee_M"}
STACKED = {
    "hat", "vee_hat", "exp", "log", "dexp", "dexpinv", "cay", "cayinv_cay", "dcay",
    "dcayinv", "defect", "defect_off_group",
}  # fmt: skip


@functools.cache
def _compiled(n):
    return jax.jit(functools.partial(_evaluate, lievi.SOn(n)), compiler_options=FAST_COMPILE)


@functools.cache
def _report(n):
    out = _compiled(n)(*(jnp.asarray(a) for a in _inputs(n)))
    return {name: np.array(value) for name, value in out.items()}


# ---- construction and coordinates ----------------------------------------------------------


def test_invalid_n_raises():
    for bad in (1, 0, 2.0):
        with pytest.raises(ValueError):
            lievi.SOn(bad)


@pytest.mark.parametrize("n", NS)
def test_hat_rejects_wrong_last_axis(n):
    group = lievi.SOn(n)
    with pytest.raises(ValueError):
        group.hat(jnp.zeros(group.algebra_dim + 1))
    with pytest.raises(ValueError):
        group.hat(jnp.zeros((2, 5, group.algebra_dim - 1)))


@pytest.mark.parametrize(
    "n",
    (2, 3, *(pytest.param(n, marks=pytest.mark.extended) for n in range(4, 9))),  # 4, 8: 9 s
)
def test_hat_vee_and_basis(n):
    """hat is skew, vee ∘ hat = id, the basis is orthonormal for ⟨X, Y⟩ = tr(XᵀY)/2,
    vee reads coordinates in it (so it projects onto the skew part), hat is linear."""
    r = _report(n)
    E = r["basis"]
    d = lievi.SOn(n).algebra_dim
    assert d == n * (n - 1) // 2
    assert E.shape == (d, n, n)
    np.testing.assert_array_equal(_inner(E[:, None], E[None, :]), np.eye(d))
    np.testing.assert_array_equal(E, r["hat_eye"])
    xy = np.stack(_inputs(n)[:2])
    np.testing.assert_array_equal(r["hat"], -np.swapaxes(r["hat"], -1, -2))
    np.testing.assert_array_equal(r["vee_hat"], xy)
    np.testing.assert_allclose(r["hat"], _hat_np(E, xy), rtol=0, atol=ROUNDOFF)
    M = _inputs(n)[-1]
    np.testing.assert_allclose(r["vee_M"], _vee_np(E, M), rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["hat_vee_M"], (M - M.T) / 2, rtol=0, atol=ROUNDOFF)


# ---- group ------------------------------------------------------------------------------------


@pytest.mark.parametrize("n", NS)
def test_group_axioms(n):
    """exp lands in SO(n); compose is the (associative) matrix product; g g⁻¹ = I."""
    group = lievi.SOn(n)
    r = _report(n)
    _, _, _, g, k, _ = _inputs(n)
    eye = np.eye(n)
    e = r["exp"]
    eyes = np.broadcast_to(eye, e.shape)
    np.testing.assert_allclose(np.swapaxes(e, -1, -2) @ e, eyes, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(np.linalg.det(e), 1.0, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["compose"], g @ k, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["compose_left"], r["compose_right"], rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(g @ r["inverse"], eyes[0], rtol=0, atol=ROUNDOFF)
    np.testing.assert_array_equal(group.identity(), eye)
    np.testing.assert_array_equal(r["compose_identity"], g)
    assert group.exp_radius == pytest.approx(np.pi)


@pytest.mark.parametrize("n", NS)
def test_exp_is_expm_of_hat(n):
    """Against scipy's expm (host side: an independent implementation)."""
    expected = scipy.linalg.expm(_report(n)["hat"])
    np.testing.assert_allclose(_report(n)["exp"], expected, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("n", NS)
def test_membership_defect(n):
    """≈ 0 on rotations; > 0 off the orthogonal group and on reflections (det = −1)."""
    r = _report(n)
    assert np.max(r["defect"]) <= ROUNDOFF  # exp(x) and random rotations
    stretched, reflected = r["defect_off_group"]
    assert np.all(stretched > 1e-4)
    assert np.all(reflected > 1.0)


# ---- algebra ----------------------------------------------------------------------------------


@pytest.mark.parametrize("n", NS)
def test_ad_and_bracket_are_the_commutator(n):
    r = _report(n)
    x, y, *_ = _inputs(n)
    E = r["basis"]
    X, Y = _hat_np(E, x), _hat_np(E, y)
    commutator = _vee_np(E, X @ Y - Y @ X)
    np.testing.assert_allclose(r["bracket"], commutator, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(_apply(r["ad_x"], y), commutator, rtol=0, atol=ROUNDOFF)
    # The commutator of skew matrices is skew: its coordinates lose nothing.
    np.testing.assert_allclose(_hat_np(E, commutator), X @ Y - Y @ X, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("n", NS)
def test_jacobi_identity(n):
    """[x,[y,z]] + [y,[z,x]] + [z,[x,y]] = 0, with brackets as the library's ad matrices."""
    r = _report(n)
    x, y, z, *_ = _inputs(n)
    ad_x, ad_y, ad_z = r["ad_x"], r["ad_y"], r["ad_z"]
    jacobi = (
        _apply(ad_x, _apply(ad_y, z))
        + _apply(ad_y, _apply(ad_z, x))
        + _apply(ad_z, _apply(ad_x, y))
    )
    np.testing.assert_allclose(jacobi, 0.0, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("n", NS)
def test_Ad_is_conjugation_and_an_automorphism(n):
    """hat(Ad(g) y) = g ŷ g⁻¹, Ad(g) is orthogonal, and Ad(g)[x, y] = [Ad(g) x, Ad(g) y]."""
    r = _report(n)
    x, y, _, g, *_ = _inputs(n)
    E = r["basis"]
    Ad = r["Ad"]
    conjugated = g @ _hat_np(E, y) @ np.swapaxes(g, -1, -2)
    np.testing.assert_allclose(_hat_np(E, _apply(Ad, y)), conjugated, rtol=0, atol=ROUNDOFF)
    eye = np.broadcast_to(np.eye(E.shape[0]), Ad.shape)
    np.testing.assert_allclose(np.swapaxes(Ad, -1, -2) @ Ad, eye, rtol=0, atol=ROUNDOFF)
    u, v = _hat_np(E, _apply(Ad, x)), _hat_np(E, _apply(Ad, y))
    np.testing.assert_allclose(
        _apply(Ad, r["bracket"]), _vee_np(E, u @ v - v @ u), rtol=0, atol=ROUNDOFF
    )


# ---- charts -----------------------------------------------------------------------------------


@pytest.mark.parametrize("n", NS)
def test_log_inverts_exp(n):
    """Random |x| ≤ 2.5, a near half-turn (π − 1e-7), a plane at 3, near identities."""
    np.testing.assert_allclose(_report(n)["log"][0], _inputs(n)[0], rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("n", NS)
def test_exp_inverts_log_on_random_rotations(n):
    """Haar-random rotations have angles anywhere in (−π, π); log must stay principal."""
    r = _report(n)
    g = _inputs(n)[3]
    X = _hat_np(r["basis"], r["log"][1])
    assert np.all(np.isfinite(X))
    np.testing.assert_allclose(scipy.linalg.expm(X), g, rtol=0, atol=ROUNDOFF)
    # Principal: every rotation angle of x̂ (eigenvalues ±iθ) at most π.
    assert np.all(np.abs(np.linalg.eigvals(X)) <= np.pi + ROUNDOFF)


@pytest.mark.parametrize("n", NS)
def test_chart_identities(n):
    """dexpinv · dexp = I, dcayinv · dcay = I, cayinv ∘ cay = id, and cay(x) is the
    Cayley transform (I − x̂/2)⁻¹(I + x̂/2)."""
    r = _report(n)
    xy = np.stack(_inputs(n)[:2])
    d = r["dexp"].shape[-1]
    eye = np.broadcast_to(np.eye(d), r["dexp"].shape)
    np.testing.assert_allclose(r["dexpinv"] @ r["dexp"], eye, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["dcayinv"] @ r["dcay"], eye, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["cayinv_cay"], xy, rtol=0, atol=ROUNDOFF)
    X, eye = r["hat"], np.eye(n)
    np.testing.assert_allclose((eye - X / 2) @ r["cay"], eye + X / 2, rtol=0, atol=ROUNDOFF)


# ---- batching ---------------------------------------------------------------------------------


@pytest.mark.parametrize("n", NS)
def test_batch_axes(n):
    """Every method takes batch shape (2, 5): the right output shapes, and each element
    equals the same method on a batch of copies of that element (no mixing)."""
    d = n * (n - 1) // 2
    r = _report(n)
    # Shapes after the batch axes. Outputs in STACKED have one more leading axis (of 2).
    expected_shapes = dict(
        hat=(n, n), vee_hat=(d,), exp=(n, n), log=(d,), dexp=(d, d), dexpinv=(d, d),
        cay=(n, n), cayinv_cay=(d,), dcay=(d, d), dcayinv=(d, d), ad_x=(d, d), Ad=(d, d),
        bracket=(d,), inverse=(n, n), compose=(n, n), defect=(), defect_off_group=(),
    )  # fmt: skip
    assert set(expected_shapes) <= set(r)
    for name, shape in expected_shapes.items():
        leading = (2,) + BATCH if name in STACKED else BATCH
        assert r[name].shape == leading + shape, name
    *batched, M = _inputs(n)
    copies = [jnp.broadcast_to(a[1, 3], a.shape) for a in batched] + [M]
    copied = {name: np.asarray(value) for name, value in _compiled(n)(*copies).items()}
    for name, value in r.items():
        if name in UNBATCHED:
            continue
        if name in STACKED:  # compare the first half of the stack (from x, exp(x), ...)
            value, other = value[0], copied[name][0]
        else:
            other = copied[name]
        expected = np.broadcast_to(value[1, 3], value.shape)
        np.testing.assert_array_equal(other, expected, err_msg=name)
