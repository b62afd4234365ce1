"""Derivatives of the group maps: finite where others give NaN, and correct.

docs/theory/closed-forms.md lists the failures seen elsewhere: NaN gradients of log at θ = π and of exp at
the identity (both branches of a `jnp.where` are differentiated), and Taylor branches
that do not join the exact forms. Here, in float32 and float64:

- jax.jacfwd (forward mode) and jax.grad (reverse mode) of exp, log, dexp, dexpinv, cay
  and log ∘ exp are finite at θ = 0, near π, and (log) at exact half-turns;
- they are right: d exp at 0 gives the basis, log ∘ exp has the identity Jacobian, and
  dexp / dcay are the right-trivialised derivatives of exp / cay (autodiff);
- values and first derivatives join across the Taylor switch.

All derivatives of one group and dtype come from one jitted function (compilation
dominates the run time); the tests read its report. The derivatives of log ∘ exp are
assembled by the chain rule from those of log (at exp(x)) and exp.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import test_son
from scipy.spatial.transform import Rotation

import lievi
from helpers import ROUNDOFF, ROUNDOFF_F32
from lievi._groups._series import small_threshold as _small_threshold

SO3 = lievi.SO3
# See test_son: level 0 halves compile time and keeps floating-point semantics.
FAST_COMPILE = test_son.FAST_COMPILE
DTYPES = (np.float32, np.float64)
TOL = {np.float32: ROUNDOFF_F32, np.float64: ROUNDOFF}
# "Near π": as close as the dtype resolves comfortably.
NEAR_PI = {np.float32: np.pi - 1e-3, np.float64: np.pi - 1e-7}
SWITCH = np.sqrt(_small_threshold(np.float64))  # exp, dexp, dexpinv: θ² = 1e-3
LOG_SWITCH = np.arctan(SWITCH)  # log: tan²θ = 1e-3
AXIS = np.array([0.36, -0.48, 0.8])  # a unit vector with no zero component
HALF_TURN = np.diag([1.0, -1.0, -1.0])
SON_NS = (4,)  # generic SO(n): compiling derivatives is costly; SOn(3) equals SO3 (test_so3)


def _angles(dtype):
    """(name, angle) along AXIS; every angle below π."""
    named = [("zero", 0.0), ("1e-9", 1e-9), ("1e-4", 1e-4), ("1", 1.0), ("3", 3.0)]
    named.append(("near_pi", NEAR_PI[dtype]))
    if dtype == np.float64:
        named += [
            ("switch-", SWITCH * (1 - 1e-12)),
            ("switch+", SWITCH * (1 + 1e-12)),
            ("log_switch-", LOG_SWITCH * (1 - 1e-12)),
            ("log_switch+", LOG_SWITCH * (1 + 1e-12)),
        ]
    return named


def _points(dtype):
    """Algebra points: the named angles along AXIS, then random ones with |x| < π."""
    rng = np.random.default_rng(7)
    special = np.array([angle for _, angle in _angles(dtype)])[:, None] * AXIS
    random = rng.normal(size=(12, 3))
    random *= rng.uniform(0.05, 3.0, size=(12, 1)) / np.linalg.norm(random, axis=-1, keepdims=True)
    return np.concatenate([special, random])


def _index(dtype, name):
    return [n for n, _ in _angles(dtype)].index(name)


def _matrices(dtype):
    """Rotations for log: the identity, an exact half-turn, then scipy's exp of every
    point (log's own report adds the library's exp of every point after these)."""
    return np.concatenate(
        [np.eye(3)[None], HALF_TURN[None], Rotation.from_rotvec(_points(dtype)).as_matrix()]
    )


def _weighted(f):
    """x ↦ Σ w ⊙ f(x) for a fixed weighting w of f's output shape: a scalar for jax.grad."""

    def scalar(x):
        value = f(x)
        w = jnp.cos(1.0 + jnp.arange(value.size, dtype=value.dtype)).reshape(value.shape)
        return jnp.sum(w * value)

    return scalar


def _weights(shape):
    """The weighting of `_weighted`, on the host."""
    return np.cos(1.0 + np.arange(int(np.prod(shape)))).reshape(shape)


def _so3_derivatives(x, M):
    """jacfwd (forward mode) and grad of a fixed weighting (reverse mode) of every map at
    the points x, and of log at the rotations M and at exp(x)."""
    maps = {"exp": SO3.exp, "dexp": SO3.dexp, "dexpinv": SO3.dexpinv, "cay": SO3.cay}
    out = {}
    for name, f in maps.items():
        out[name + "/jacfwd"] = jax.vmap(jax.jacfwd(f))(x)
        out[name + "/grad"] = jax.vmap(jax.grad(_weighted(f)))(x)
        out[name + "/value"] = f(x)
    out["dcay/value"] = SO3.dcay(x)
    rotations = jnp.concatenate([M, SO3.exp(x)])
    out["log/jacfwd"] = jax.vmap(jax.jacfwd(SO3.log))(rotations)
    out["log/grad"] = jax.vmap(jax.grad(_weighted(SO3.log)))(rotations)
    out["log/value"] = SO3.log(rotations)
    return out


def _with_log_exp(report, points):
    """Derivatives of log ∘ exp at the points, by the chain rule from those of log at
    exp(x) and of exp at x (what autodiff does through the composition; compiling the
    composition again would double the compile time of the report)."""
    at_exp = slice(len(report["log/value"]) - points, None)
    jac_log, jac_exp = report["log/jacfwd"][at_exp], report["exp/jacfwd"]
    report["log_exp/jacfwd"] = np.einsum("pbij,pija->pba", jac_log, jac_exp)
    report["log_exp/grad"] = np.einsum("pij,pija->pa", report["log/grad"][at_exp], jac_exp)
    report["log_exp/value"] = report["log/value"][at_exp]
    return report


def _son_derivatives(group, x):
    """Forward-mode Jacobians of exp and cay at x; jacfwd and grad of log at exp(x).
    (dexp and dexpinv are not differentiated here: their closed forms on SO(3) are, and
    SOn(3) equals them in test_so3.)"""
    e = group.exp(x)
    return {
        "exp/jacfwd": jax.vmap(jax.jacfwd(group.exp))(x),
        "exp/value": e,
        "cay/jacfwd": jax.vmap(jax.jacfwd(group.cay))(x),
        "cay/value": group.cay(x),
        "log/jacfwd": jax.vmap(jax.jacfwd(group.log))(e),
        "log/grad": jax.vmap(jax.grad(_weighted(group.log)))(e),
        "log/value": group.log(e),
    }


def _host(out, dtype):
    for name, value in out.items():
        assert value.dtype == dtype, name
    return {name: np.array(value) for name, value in out.items()}


@functools.cache
def _so3_report(dtype):
    x, M = (jnp.asarray(a, dtype) for a in (_points(dtype), _matrices(dtype)))
    report = _host(jax.jit(_so3_derivatives, compiler_options=FAST_COMPILE)(x, M), dtype)
    return _with_log_exp(report, len(x))


@functools.cache
def _son_report(n):
    """On the samples of test_son's report for SOn(n), flattened: 0, 1e-9, 1e-4, both
    sides of θ² = 1e-3, a plane at 3 and at π − 1e-7, random with |x| ≤ 2.5."""
    x = jnp.asarray(test_son._inputs(n)[0].reshape(-1, n * (n - 1) // 2))
    derivatives = functools.partial(_son_derivatives, lievi.SOn(n))
    report = _host(jax.jit(derivatives, compiler_options=FAST_COMPILE)(x), np.float64)
    return _with_log_exp(report, len(x))


def _right_trivialised(group, jac, value):
    """Columns vee(∂_a chart · chart⁻¹) from a batched forward Jacobian (…, n, n, d) of
    an orthogonal-valued chart (chart⁻¹ = chartᵀ), on the host."""
    E = np.asarray(group.basis())
    products = np.einsum("...ija,...kj->...aik", jac, value)  # ∂_a chart · chartᵀ
    return np.swapaxes(np.einsum("bik,...aik->...ab", E, products) / 2, -1, -2)


def _not_finite(report):
    return [name for name, value in report.items() if not np.all(np.isfinite(value))]


# ---- finite --------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_so3_derivatives_are_finite(dtype):
    """At θ = 0, 1e-9, near π, at the identity and at an exact half-turn (log), and
    elsewhere: no NaN or inf in any jacfwd or grad."""
    assert _not_finite(_so3_report(dtype)) == []


@pytest.mark.extended  # 8 s
@pytest.mark.parametrize("n", SON_NS)
def test_son_derivatives_are_finite(n):
    """At 0, 1e-9, a plane at π − 1e-7, and the other samples."""
    assert _not_finite(_son_report(n)) == []


# ---- correct -------------------------------------------------------------------------------


def _check_exp_derivative_at_zero(jac, grad, group, dtype, tol):
    """d exp(x)/dx_a at 0 is the basis matrix E_a."""
    E = np.asarray(group.basis(dtype))
    np.testing.assert_allclose(np.moveaxis(jac, -1, 0), E, rtol=0, atol=tol)
    if grad is not None:  # grad of Σ w ⊙ exp(x) at 0 is (Σ w ⊙ E_a)_a.
        expected = np.einsum("ij,aij->a", _weights(E[0].shape), E)
        np.testing.assert_allclose(grad, expected, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_so3_exp_derivative_at_identity_is_the_basis(dtype):
    r = _so3_report(dtype)
    i = _index(dtype, "zero")
    _check_exp_derivative_at_zero(r["exp/jacfwd"][i], r["exp/grad"][i], SO3, dtype, TOL[dtype])


@pytest.mark.extended  # 19 s
@pytest.mark.parametrize("n", SON_NS)
def test_son_exp_derivative_at_identity_is_the_basis(n):
    jac = _son_report(n)["exp/jacfwd"][0]  # test_son puts x = 0 first
    _check_exp_derivative_at_zero(jac, None, lievi.SOn(n), np.float64, ROUNDOFF)


def _check_log_exp_jacobian(report, d, tol):
    """Jacobian of log ∘ exp is I at every point (all have |x| < π); its weighted grad is w."""
    jac = report["log_exp/jacfwd"]
    np.testing.assert_allclose(jac, np.broadcast_to(np.eye(d), jac.shape), rtol=0, atol=tol)
    w = np.broadcast_to(_weights((d,)), (len(jac), d))
    np.testing.assert_allclose(report["log_exp/grad"], w, rtol=0, atol=tol)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_so3_log_exp_jacobian_is_identity(dtype):
    """At 0, 1e-9, 1e-4, 1, 3, near π, both sides of the switch points, random."""
    _check_log_exp_jacobian(_so3_report(dtype), 3, TOL[dtype])


@pytest.mark.parametrize("n", SON_NS)
def test_son_log_exp_jacobian_is_identity(n):
    """SOn.log ends with a Newton step whose derivative is the exact one, also near π."""
    _check_log_exp_jacobian(_son_report(n), lievi.SOn(n).algebra_dim, ROUNDOFF)


@pytest.mark.parametrize("dtype", DTYPES, ids=["f32", "f64"])
def test_so3_log_at_identity_and_half_turn(dtype):
    """log I = 0 with d log(I)[Ê] = e along the basis, and |log| = π at the exact
    half-turn (whose derivatives are checked finite above)."""
    r = _so3_report(dtype)
    np.testing.assert_array_equal(r["log/value"][0], 0.0)
    np.testing.assert_allclose(np.linalg.norm(r["log/value"][1]), np.pi, rtol=0, atol=TOL[dtype])
    E = np.asarray(SO3.basis(dtype))
    along = np.einsum("aij,bij->ab", r["log/jacfwd"][0], E)  # column b: d log(I)[E_b]
    np.testing.assert_allclose(along, np.eye(3), rtol=0, atol=TOL[dtype])


@pytest.mark.parametrize("chart", ["exp", "cay"])
def test_so3_chart_derivative_is_right_trivialised(chart):
    """dexp(x) y = vee(d/dε exp(x + εy) · exp(x)⁻¹), likewise dcay, at every point."""
    r = _so3_report(np.float64)
    autodiff = _right_trivialised(SO3, r[chart + "/jacfwd"], r[chart + "/value"])
    np.testing.assert_allclose(r[f"d{chart}/value"], autodiff, rtol=0, atol=ROUNDOFF)


@pytest.mark.parametrize("chart", ["exp", "cay"])
@pytest.mark.parametrize("n", SON_NS)
def test_son_chart_derivative_is_right_trivialised(n, chart):
    """Against the generic dexp / dcay of test_son's report at the same points."""
    group = lievi.SOn(n)
    r = _son_report(n)
    autodiff = _right_trivialised(group, r[chart + "/jacfwd"], r[chart + "/value"])
    expected = test_son._report(n)[f"d{chart}"][0]  # the x half of its stack
    np.testing.assert_allclose(autodiff, expected.reshape(autodiff.shape), rtol=0, atol=ROUNDOFF)


# ---- Taylor switch ---------------------------------------------------------------------


@pytest.mark.parametrize("name", ["exp", "dexp", "dexpinv", "log_exp"])
@pytest.mark.parametrize("mode", ["value", "jacfwd", "grad"])
def test_taylor_switch_is_continuous(name, mode):
    """float64: values and first derivatives just below and above θ² = 1e-3 (exp, dexp,
    dexpinv) and tan²θ = 1e-3 (log) agree to round-off. A wrong Taylor coefficient, or a
    series for a different function than the exact branch, breaks this."""
    r = _so3_report(np.float64)
    switch = "log_switch" if name == "log_exp" else "switch"
    below, above = (r[f"{name}/{mode}"][_index(np.float64, switch + side)] for side in "-+")
    np.testing.assert_allclose(below, above, rtol=0, atol=ROUNDOFF)


def test_log_derivative_is_continuous_off_the_group():
    """The derivative of log with respect to all nine entries of g (also off the group,
    as when g is a free parameter) joins across log's Taylor switch."""
    r = _so3_report(np.float64)
    i = 2 + _index(np.float64, "log_switch-")  # _matrices puts I and a half-turn first
    for mode in ("jacfwd", "grad"):
        np.testing.assert_allclose(
            r["log/" + mode][i], r["log/" + mode][i + 1], rtol=0, atol=ROUNDOFF, err_msg=mode
        )
