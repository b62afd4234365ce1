"""Property-based tests (hypothesis): invariances and agreements that must hold for every
body, every unit system and every bad input, not only for the hand-picked cases.

Settings: `max_examples` 10–40 per property, `deadline=None`, derandomized (the first
example of a property compiles the run; later ones reuse it). Each property compiles once
per method, which is where the time goes, so the default profile samples few methods;
the `slow` profiles (40–60 examples, every method) cover the rest. Shapes are fixed inside a property so that examples never recompile.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

import lievi
from helpers import random_rotation

SETTINGS = dict(deadline=None, suppress_health_check=[HealthCheck.too_slow], derandomize=True)

IMPLICIT = {
    "dep-exp": lievi.DEP(chart="exp"),
    "dep-cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
    "composition-mv": lievi.Composition(lievi.MoserVeselov(), order=4),
    "preprocessed": lievi.PreprocessedMoserVeselov(order=4),
}

moments = st.tuples(*[st.floats(0.2, 5.0)] * 3)
directions = st.tuples(*[st.floats(-1.0, 1.0)] * 3).filter(lambda v: np.linalg.norm(v) > 0.1)


def _state(inertia, direction, angle_per_step, dtype):
    """A body, its momentum, and the step `h` that turns it by `angle_per_step`."""
    inertia = np.asarray(inertia)
    m0 = np.asarray(direction)
    h = angle_per_step / np.linalg.norm(m0 / inertia)
    return jnp.asarray(inertia, dtype), jnp.asarray(m0, dtype), jnp.asarray(h, dtype)


def _scale_invariance(name, inertia, direction, exponent, dtype, atol):
    integrator = IMPLICIT[name]
    inertia, m0, h = _state(inertia, direction, 0.3, dtype)
    g0 = jnp.eye(3, dtype=dtype)
    c = jnp.asarray(10.0**exponent, dtype)
    ref = lievi.simulate(lievi.RigidBody(inertia), integrator, g0, m0, h=h, n_steps=4, throw=False)
    # (I, Π) → (cI, cΠ)
    units = lievi.simulate(
        lievi.RigidBody(inertia * c), integrator, g0, m0 * c, h=h, n_steps=4, throw=False
    )
    # (h, Π) → (h/c, cΠ): the same increments
    time = lievi.simulate(
        lievi.RigidBody(inertia), integrator, g0, m0 * c, h=h / c, n_steps=4, throw=False
    )
    assert int(ref.result) == 0
    for sol in (units, time):
        assert int(sol.result) == 0
        np.testing.assert_allclose(sol.g, ref.g, rtol=0, atol=atol)
        np.testing.assert_allclose(
            sol.m / c, ref.m, rtol=0, atol=atol * float(jnp.max(jnp.abs(m0)))
        )


@pytest.mark.extended  # 11 s
@settings(max_examples=25, **SETTINGS)
@given(
    name=st.sampled_from(["dep-exp", "dep-cayley", "moser-veselov"]),
    inertia=moments,
    direction=directions,
    exponent=st.floats(-15.0, 15.0),
)
def test_scale_invariance_float64(name, inertia, direction, exponent):
    _scale_invariance(name, inertia, direction, exponent, jnp.float64, 1e-11)


@pytest.mark.extended  # 15 s
@settings(max_examples=15, **SETTINGS)
@given(
    name=st.sampled_from(["dep-exp", "moser-veselov"]),
    inertia=moments,
    direction=directions,
    exponent=st.floats(-6.0, 6.0),
)
def test_scale_invariance_float32(name, inertia, direction, exponent):
    _scale_invariance(name, inertia, direction, exponent, jnp.float32, 2e-5)


@pytest.mark.slow
@settings(max_examples=60, **SETTINGS)
@given(
    name=st.sampled_from(list(IMPLICIT)),
    inertia=moments,
    direction=directions,
    exponent=st.floats(-15.0, 15.0),
)
def test_scale_invariance_every_implicit_method(name, inertia, direction, exponent):
    _scale_invariance(name, inertia, direction, exponent, jnp.float64, 1e-11)


# ---- log ∘ exp and exp ∘ log near 0 and π --------------------------------------------------

angles = st.one_of(
    st.floats(0.0, 1e-3),  # near the identity
    st.floats(-15.0, -1.0).map(lambda e: np.pi - 10.0**e),  # near a half-turn
    st.just(np.pi),  # at a half-turn
    st.floats(0.0, np.pi),
)


@settings(max_examples=40, **SETTINGS)
@given(direction=directions, angle=angles)
def test_so3_log_exp_round_trip(direction, angle):
    axis = np.asarray(direction) / np.linalg.norm(direction)
    x = jnp.asarray(angle * axis)
    g = lievi.SO3.exp(x)
    y = lievi.SO3.log(g)
    np.testing.assert_allclose(lievi.SO3.exp(y), g, rtol=0, atol=1e-14)
    if angle < np.pi - 1e-6:  # below π the principal log is unique: log ∘ exp = id
        np.testing.assert_allclose(y, x, rtol=0, atol=1e-12)


@functools.cache
def _son_round_trip(n):
    group = lievi.SOn(n)

    @jax.jit
    def run(R, angles):
        """Rotations `R diag(planes at angles) Rᵀ`; their log and its exp."""
        d = group.algebra_dim
        x = jnp.zeros(d, R.dtype)
        block = jnp.zeros((n, n), R.dtype)
        for p in range(n // 2):
            block = block.at[2 * p + 1, 2 * p].set(angles[p]).at[2 * p, 2 * p + 1].set(-angles[p])
        g = R @ jax.scipy.linalg.expm(block) @ R.T
        x = group.log(g)
        return g, x, group.exp(x)

    return run


@pytest.mark.extended  # 11 s
@settings(max_examples=20, **SETTINGS)
@given(
    n=st.sampled_from([2, 4]),
    seed=st.integers(0, 2**31 - 1),
    first=angles,
    second=st.floats(0.0, 3.0),
)
def test_son_log_is_exact_or_nan_near_half_turns(n, seed, first, second):
    """`SOn.log` returns `x` with `exp(x) = g` to round-off, never a wrong finite number."""
    R = random_rotation(np.random.default_rng(seed), n)
    g, x, e = _son_round_trip(n)(R, jnp.asarray([first, second][: n // 2]))
    assert np.all(np.isfinite(np.asarray(x)))  # one half-turn plane at most: always exact
    np.testing.assert_allclose(e, g, rtol=0, atol=256 * n * np.finfo(float).eps)


# ---- traced and eager validation agree ---------------------------------------------------------

BAD_INPUTS = {
    "negative inertia": dict(inertia=np.array([-1.0, 1.0, 1.0])),
    "zero inertia": dict(inertia=np.array([0.0, 1.0, 1.0])),
    "nan inertia": dict(inertia=np.array([np.nan, 1.0, 1.0])),
    "indefinite tensor": dict(
        inertia=np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    ),
    "non-symmetric tensor": dict(
        inertia=np.array([[1.0, 0.5, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]])
    ),
    "scaled g0": dict(g0=2 * np.eye(3)),
    "reflection g0": dict(g0=np.diag([1.0, 1.0, -1.0])),
    "nan g0": dict(g0=np.full((3, 3), np.nan)),
    "nan m0": dict(m0=np.array([np.nan, 0.0, 1.0])),
    "zero h": dict(h=0.0),
    "negative h": dict(h=-0.1),
    "nan h": dict(h=np.nan),
}


def _case(bad, scale):
    inputs = dict(
        inertia=np.array([2.0, 1.0, 2.0 / 3.0]) * scale,
        g0=np.eye(3),
        m0=np.array([np.cos(1.1), 0.0, np.sin(1.1)]) * scale,
        h=0.1,
    )
    inputs.update(BAD_INPUTS[bad])
    if inputs["inertia"].ndim == 2 and bad != "nan inertia":
        inputs["inertia"] = inputs["inertia"] * scale
    return inputs


@functools.cache
def _traced_run(integrator, tensor):
    del tensor  # part of the cache key: a (3,) and a (3, 3) inertia compile separately

    @jax.jit
    def run(inertia, g0, m0, h):
        body = lievi.RigidBody(inertia)
        return lievi.simulate(body, integrator, g0, m0, h=h, n_steps=2, throw=False).result

    return run


@pytest.mark.extended  # 16 s
@settings(max_examples=25, **SETTINGS)
@given(bad=st.sampled_from(list(BAD_INPUTS)), scale=st.floats(1e-3, 1e3))
def test_traced_and_eager_validation_agree(bad, scale):
    """A bad input raises `ValueError` eagerly and gives `invalid_input` under `jit`,
    on the generic path and on the batched fast path — never `successful`."""
    _validation_agrees(bad, "dep-exp", scale)


@pytest.mark.slow
@settings(max_examples=60, **SETTINGS)
@given(
    bad=st.sampled_from(list(BAD_INPUTS)),
    name=st.sampled_from(list(IMPLICIT)[:3]),
    scale=st.floats(1e-6, 1e6),
)
def test_traced_and_eager_validation_agree_every_method(bad, name, scale):
    _validation_agrees(bad, name, scale)


def _validation_agrees(bad, name, scale):
    integrator = IMPLICIT[name]
    x = _case(bad, scale)
    with pytest.raises(ValueError):
        lievi.simulate(
            lievi.RigidBody(x["inertia"]), integrator, x["g0"], x["m0"], h=x["h"], n_steps=2
        )
    run = _traced_run(integrator, x["inertia"].ndim == 2)
    result = run(*(jnp.asarray(x[k], float) for k in ("inertia", "g0", "m0", "h")))
    assert int(result) == lievi.RESULTS.invalid_input
    if x["inertia"].ndim == 1:
        bodies = jax.vmap(lievi.RigidBody)(
            jnp.asarray(np.stack([x["inertia"], [2.0, 1.0, 2.0 / 3.0]]))
        )
        good = _case("zero h", 1.0)  # only its g0, m0 are used
        g0 = jnp.asarray(np.stack([x["g0"], good["g0"]]))
        m0 = jnp.asarray(np.stack([x["m0"], good["m0"] * 1.0]))
        h = jnp.asarray([x["h"], 0.1])
        batch = _traced_batch(integrator)(bodies, g0, m0, h)
        assert [int(r) for r in batch] == [lievi.RESULTS.invalid_input, 0]


@functools.cache
def _traced_batch(integrator):
    @jax.jit
    def run(bodies, g0, m0, h):
        return lievi.simulate_batch(
            bodies,
            integrator,
            g0,
            m0,
            h=h,
            n_steps=2,
            system_axis=0,
            throw=False,
            save=lievi.Save(every=2),
        ).result

    return run


# ---- fast path = generic path up to the step bound ---------------------------------------------

BATCH = 24
FAST = {
    "dep-exp": lievi.DEP(chart="exp"),
    "dep-cayley": lievi.DEP(chart="cayley"),
    "moser-veselov": lievi.MoserVeselov(),
    "splitting": lievi.LiePoissonSplitting(),
    "rk4": lievi.RK4(),
}


def _fast_equals_generic(name, seed, fraction):
    integrator = FAST[name]
    rng = np.random.default_rng(seed)
    inertia = rng.uniform(0.3, 3.0, (BATCH, 3))
    m0 = rng.normal(size=(BATCH, 3))
    # Angles per step up to `fraction` of the documented bound, and a few beyond it.
    angle = rng.uniform(0.0, fraction * integrator.step_bound(), BATCH)
    h = angle / np.linalg.norm(m0 / inertia, axis=1)
    bodies = jax.vmap(lievi.RigidBody)(jnp.asarray(inertia))
    g0 = jnp.asarray(np.stack([random_rotation(rng, 3) for _ in range(BATCH)]))
    args = (bodies, integrator, g0, jnp.asarray(m0))
    kwargs = dict(h=jnp.asarray(h), n_steps=3, save=lievi.Save(), system_axis=0, throw=False)
    fast = lievi.simulate_batch(*args, tuning=lievi.advanced.Tuning(fast=True), **kwargs)
    generic = lievi.simulate_batch(*args, tuning=lievi.advanced.Tuning(fast=False), **kwargs)
    np.testing.assert_array_equal(fast.result, generic.result)
    ok = np.asarray(generic.result) == 0
    np.testing.assert_allclose(fast.g[ok], generic.g[ok], rtol=0, atol=1e-10)
    np.testing.assert_allclose(fast.m[ok], generic.m[ok], rtol=0, atol=1e-10 * np.abs(m0).max())
    beyond = angle > integrator.step_bound()
    assert np.all(np.asarray(fast.result)[beyond] == lievi.RESULTS.step_too_large)


@pytest.mark.extended  # 9 s
@settings(max_examples=10, **SETTINGS)
@given(seed=st.integers(0, 2**31 - 1))
def test_fast_path_equals_generic_path(seed):
    """Moser–Veselov, whose two paths solve differently (quartic vs Newton in x): the
    same branch, hence the same code and iterates, for every body."""
    _fast_equals_generic("moser-veselov", seed, fraction=1.2)


@pytest.mark.slow
@settings(max_examples=40, **SETTINGS)
@given(name=st.sampled_from(list(FAST)), seed=st.integers(0, 2**31 - 1))
def test_fast_path_equals_generic_path_every_method(name, seed):
    _fast_equals_generic(name, seed, fraction=1.2)
