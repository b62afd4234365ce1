"""SO(3) closed forms: values against scipy and against the generic matrix-group code.

Float64 unless a test says otherwise. The angles include the places where closed forms
break elsewhere (docs/theory/closed-forms.md): 0, tiny angles, both sides of the Taylor switches (θ² = 1e-3
for exp/dexp/dexpinv, tan²θ = 1e-3 for log, in float64), and θ → π, where `sin θ`
carries no axis information. Compilation dominates the run time, so every method runs
once, in one jitted function per dtype on one batch of samples, and the tests check that
report on the host. Derivatives are tested in `test_group_autodiff.py`.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
import test_son
from scipy.spatial.transform import Rotation

import lievi
from helpers import ROUNDOFF, ROUNDOFF_F32, random_rotation
from lievi._groups._series import small_threshold as _small_threshold

SO3 = lievi.SO3
# float32 against float64: the spec asks for 1e-5 (~100 ulps at magnitude 1); the
# largest error measured over these samples is ~1.4e-7.
F32_VS_F64 = ROUNDOFF_F32 / 10
# See test_son: level 0 halves compile time and keeps floating-point semantics.
FAST_COMPILE = test_son.FAST_COMPILE

SWITCH = np.sqrt(_small_threshold(np.float64))
LOG_SWITCH = np.arctan(SWITCH)
ANGLES = (
    0.0,
    1e-9,
    1e-4,
    0.0316,
    LOG_SWITCH * (1 - 1e-12),
    LOG_SWITCH * (1 + 1e-12),
    SWITCH * (1 - 1e-12),
    SWITCH * (1 + 1e-12),
    0.03163,
    0.5,
    1.0,
    2.0,
    3.0,
    np.pi - 1e-4,
    np.pi - 1e-7,
)
AXES_PER_ANGLE = 8  # the three coordinate axes, one negative axis, four random axes
RANDOM = 60  # then random rotation vectors, |ξ| uniform in [0, π)

# Exact half-turns: vee(g) = 0 and (g + gᵀ)/2 carries the axis.
HALF_TURNS = np.stack(
    [np.diag([1.0, -1.0, -1.0]), np.diag([-1.0, 1.0, -1.0]), np.diag([-1.0, -1.0, 1.0])]
)
# Rounding can push tr g above 3, where acos((tr g − 1)/2) is NaN.
TINY = np.array([1e-9, -2e-9, 0.5e-9])
TRACE_ABOVE_3 = np.stack([Rotation.from_rotvec(TINY).as_matrix(), np.eye(3)]) * (1 + 4e-16)
# Where each kind of rotation sits in the samples R (see _samples).
RANDOM_R, HALF_TURN_R, TRACE_R = slice(0, 40), slice(40, 53), slice(53, 55)


def _unit(rng, count):
    a = rng.normal(size=(count, 3))
    return a / np.linalg.norm(a, axis=-1, keepdims=True)


@functools.cache
def _samples():
    """x: every angle of ANGLES along AXES_PER_ANGLE axes, then RANDOM random rotation
    vectors; y: random vectors; R: rotations for log (40 Haar-random, the 3 exact
    half-turns, 10 half-turns up to rounding, TRACE_ABOVE_3); S: scipy's exp(x)."""
    rng = np.random.default_rng(0)
    axes = np.concatenate([np.eye(3), -np.eye(3)[:1], _unit(rng, 4)])
    special = (np.asarray(ANGLES)[:, None, None] * axes[None]).reshape(-1, 3)
    random = _unit(rng, RANDOM) * rng.uniform(0, np.pi, size=(RANDOM, 1))
    x = np.concatenate([special, random])
    y = rng.normal(size=x.shape)
    R = np.concatenate(
        [
            np.stack([random_rotation(rng, 3) for _ in range(40)]),
            HALF_TURNS,
            Rotation.from_rotvec(np.pi * _unit(rng, 10)).as_matrix(),
            TRACE_ABOVE_3,
        ]
    )
    return x, y, R, Rotation.from_rotvec(x).as_matrix()


def _evaluate(x, y, R, S):
    """Every method once, batched."""
    e = SO3.exp(x)
    c = SO3.cay(x)
    return dict(
        hat=SO3.hat(x),
        exp=e,
        log_exp=SO3.log(e),
        log_R=SO3.log(R),
        log_scipy=SO3.log(S),
        dexp=SO3.dexp(x),
        dexpinv=SO3.dexpinv(x),
        cay=c,
        cayinv_cay=SO3.cayinv(c),
        dcay=SO3.dcay(x),
        dcayinv=SO3.dcayinv(x),
        ad=SO3.ad(x),
        Ad=SO3.Ad(e),
        bracket=SO3.bracket(x, y),
        hat_Ad_y=SO3.hat(jnp.einsum("...ab,...b->...a", SO3.Ad(e), y)),
        hat_y=SO3.hat(y),
        defect=SO3.membership_defect(e),
    )


_compiled_evaluate = jax.jit(_evaluate, compiler_options=FAST_COMPILE)


@functools.cache
def _report(dtype=np.float64, at_float32_samples=False):
    """`_evaluate` on the samples in `dtype`. With `at_float32_samples`, at the samples
    rounded to float32 (the float64 reference for the float32 test)."""
    samples = _samples()
    if at_float32_samples:
        samples = [np.asarray(a, np.float32) for a in samples]
    out = _compiled_evaluate(*(jnp.asarray(a, dtype) for a in samples))
    assert all(v.dtype == dtype for v in out.values()), "dtype not preserved"
    return {name: np.array(value) for name, value in out.items()}


def _apply(M, y):
    return np.einsum("...ab,...b->...a", M, y)


# ---- exp and log against scipy --------------------------------------------------------


def test_exp_matches_scipy():
    x, _, _, S = _samples()
    np.testing.assert_allclose(_report()["exp"], S, rtol=0, atol=ROUNDOFF)


def test_log_matches_scipy():
    """All angles below π, where the rotation vector is unique."""
    x, _, _, S = _samples()
    expected = Rotation.from_matrix(S).as_rotvec()
    np.testing.assert_allclose(_report()["log_scipy"], expected, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(expected, x, rtol=0, atol=ROUNDOFF)  # scipy is consistent


def test_log_inverts_exp():
    """`log(exp ξ) = ξ` for |ξ| < π (random and special angles, batched)."""
    np.testing.assert_allclose(_report()["log_exp"], _samples()[0], rtol=0, atol=ROUNDOFF)


def test_exp_inverts_log_including_half_turns():
    """`exp(log R) = R` for Haar-random R, exact half-turns and half-turns up to rounding;
    log is principal, |ξ| ≤ π, and |ξ| = π on the half-turns."""
    R = _samples()[2]
    x = _report()["log_R"]
    assert np.all(np.isfinite(x))
    rotations = slice(0, TRACE_R.start)  # all but the slightly non-orthogonal TRACE_ABOVE_3
    back = Rotation.from_rotvec(x[rotations]).as_matrix()
    np.testing.assert_allclose(back, R[rotations], rtol=0, atol=ROUNDOFF)
    norms = np.linalg.norm(x, axis=-1)
    assert np.all(norms <= np.pi + ROUNDOFF)
    np.testing.assert_allclose(norms[HALF_TURN_R], np.pi, rtol=0, atol=ROUNDOFF)


def test_log_when_trace_exceeds_three():
    """An `acos` of (tr g − 1)/2 would give NaN here; log must give the tiny angle."""
    assert np.all(np.trace(TRACE_ABOVE_3, axis1=-2, axis2=-1) > 3)
    np.testing.assert_allclose(
        _report()["log_R"][TRACE_R], [TINY, np.zeros(3)], rtol=0, atol=ROUNDOFF
    )


# ---- closed forms against the generic base-class code (SOn(3)) -----------------------


def test_hat_is_the_cross_product():
    x, y, _, _ = _samples()
    r = _report()
    np.testing.assert_allclose(_apply(r["hat"], y), np.cross(x, y), rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["bracket"], np.cross(x, y), rtol=0, atol=ROUNDOFF)
    with pytest.raises(ValueError):
        SO3.hat(jnp.zeros((2, 4)))


def _evaluate_like_son_report(x, y, g):
    """The closed forms on the inputs of test_son's SOn(3) report, in its layout."""
    xy = jnp.stack([x, y])
    return dict(
        basis=SO3.basis(),
        hat=SO3.hat(xy),
        exp=SO3.exp(xy),
        log=SO3.log(jnp.stack([SO3.exp(x), g])),
        dexp=SO3.dexp(xy),
        dexpinv=SO3.dexpinv(xy),
        cay=SO3.cay(xy),
        dcay=SO3.dcay(xy),
        dcayinv=SO3.dcayinv(xy),
        ad_x=SO3.ad(x),
        Ad=SO3.Ad(g),
        cayinv_cay=SO3.cayinv(SO3.cay(xy)),
    )


@functools.cache
def _closed_on_son3_samples():
    x, y, _, g, *_ = (jnp.asarray(a) for a in test_son._inputs(3))
    return jax.jit(_evaluate_like_son_report, compiler_options=FAST_COMPILE)(x, y, g)


@pytest.mark.extended  # 10 s
def test_son3_coordinates_are_so3_coordinates():
    """SOn(3) and SO3 share hat, hence the basis and all coordinates, exactly."""
    closed, generic = _closed_on_son3_samples(), test_son._report(3)
    np.testing.assert_array_equal(closed["basis"], generic["basis"])
    np.testing.assert_array_equal(closed["hat"], generic["hat"])


@pytest.mark.parametrize(
    "method",
    ["exp", "log", "dexp", "dexpinv", "cay", "dcay", "dcayinv", "ad_x", "Ad", "cayinv_cay"],
)
def test_closed_form_matches_generic(method):
    """On the SOn(3) samples of test_son (0, 1e-9, 1e-4, both sides of θ² = 1e-3, planes
    at 3 and π − 1e-7, random): a wrong Taylor coefficient (docs/theory/closed-forms.md) shows here, because
    the generic forms use no series."""
    np.testing.assert_allclose(
        _closed_on_son3_samples()[method], test_son._report(3)[method], rtol=0, atol=ROUNDOFF
    )


# ---- identities between the operators -------------------------------------------------


def test_chart_identities():
    """dexpinv = dexp⁻¹, dcayinv = dcay⁻¹, cayinv ∘ cay = id, cay is the Cayley transform."""
    r = _report()
    x = _samples()[0]
    eye = np.broadcast_to(np.eye(3), r["dexp"].shape)
    np.testing.assert_allclose(r["dexpinv"] @ r["dexp"], eye, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["dcayinv"] @ r["dcay"], eye, rtol=0, atol=ROUNDOFF)
    np.testing.assert_allclose(r["cayinv_cay"], x, rtol=0, atol=ROUNDOFF)
    X = r["hat"]
    np.testing.assert_allclose((eye - X / 2) @ r["cay"], eye + X / 2, rtol=0, atol=ROUNDOFF)


def test_Ad_ad_and_exp():
    """Ad(exp ξ) = expm(ad ξ) (scipy), hat(Ad(g) y) = g ŷ g⁻¹, ad ξ = ξ̂, exp = expm ∘ hat,
    and exp lands in the group."""
    r = _report()
    g = r["exp"]
    np.testing.assert_allclose(r["Ad"], scipy.linalg.expm(r["ad"]), rtol=0, atol=ROUNDOFF)
    conjugated = g @ r["hat_y"] @ np.swapaxes(g, -1, -2)
    np.testing.assert_allclose(r["hat_Ad_y"], conjugated, rtol=0, atol=ROUNDOFF)
    np.testing.assert_array_equal(r["ad"], r["hat"])
    np.testing.assert_allclose(g, scipy.linalg.expm(r["hat"]), rtol=0, atol=ROUNDOFF)
    assert np.max(r["defect"]) <= ROUNDOFF
    assert SO3.exp_radius == pytest.approx(np.pi)


@pytest.mark.parametrize("name", ["exp", "dexp", "dexpinv", "log_exp"])
def test_taylor_switch_values_are_continuous(name):
    """Values just below and above each switch agree to round-off (the arguments differ
    by ~1e-14): every series matches its exact form where it takes over."""
    value = _report()[name][: len(ANGLES) * AXES_PER_ANGLE]
    value = value.reshape((len(ANGLES), AXES_PER_ANGLE) + value.shape[1:])
    for below in (ANGLES.index(LOG_SWITCH * (1 - 1e-12)), ANGLES.index(SWITCH * (1 - 1e-12))):
        np.testing.assert_allclose(value[below], value[below + 1], rtol=0, atol=ROUNDOFF)


# ---- float32 ---------------------------------------------------------------------------


def test_float32_matches_float64():
    """Every method in float32 (own Taylor switch at θ² = 0.1) against float64 at the same,
    float32-representable, samples (angles 0 … π − 1e-7 and random).

    Within float32 resolution of π the sign of log is ambiguous (ξ and −ξ give the same
    rotation there), so near π log is checked by exp(log R) = R instead."""
    single, exact = _report(np.float32, True), _report(np.float64, True)
    for name in ("exp", "dexp", "dexpinv", "cay", "dcay", "dcayinv", "log_scipy"):
        single_value, exact_value = single[name], exact[name]
        if name == "log_scipy":  # away from π only
            away = np.linalg.norm(exact_value, axis=-1) < np.pi - 1e-3
            single_value, exact_value = single_value[away], exact_value[away]
        np.testing.assert_allclose(single_value, exact_value, rtol=0, atol=F32_VS_F64, err_msg=name)
    np.testing.assert_allclose(
        single["log_R"][RANDOM_R], exact["log_R"][RANDOM_R], rtol=0, atol=F32_VS_F64
    )
    # Near and at π: exp(log R) = R, |log R| = the angle.
    x, _, R, S = (np.asarray(a, np.float32) for a in _samples())
    near = np.linalg.norm(exact["log_scipy"], axis=-1) >= np.pi - 1e-3
    for logs, rotations in ((single["log_scipy"][near], S[near]), (single["log_R"], R)):
        back = Rotation.from_rotvec(logs.astype(np.float64)).as_matrix()
        np.testing.assert_allclose(back, rotations, rtol=0, atol=ROUNDOFF_F32)
    np.testing.assert_allclose(
        np.linalg.norm(single["log_R"][HALF_TURN_R], axis=-1), np.pi, rtol=0, atol=F32_VS_F64
    )
