"""The eager run's programs are compiled with XLA's small-run options for one body or two
and for systems of several bodies (`lievi/_compile.py`): the policy, and the numbers, which
must not depend on it."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi import _compile, _simulate_generic, _simulate_kernel


@pytest.fixture(params=["kernel", "generic"])
def program(request):
    return {"kernel": _simulate_kernel._block, "generic": _simulate_generic._block}[request.param]


def test_small_runs_take_the_small_run_options(program):
    # On this CPU, with the installed XLA, the options are accepted (if a new XLA drops
    # them, every program keeps XLA's defaults and this test says so).
    assert _compile.small_run_options_apply()
    assert program.for_bodies(1) is program.small
    assert program.for_bodies(_compile.SMALL_RUN_BODIES) is program.small
    assert program.for_bodies(_compile.SMALL_RUN_BODIES + 1) is program.default
    # Systems of several bodies (a batch of 64 binaries), whatever their number.
    assert program.for_bodies(128, per_system=2) is program.small
    assert program.for_bodies(128, per_system=1) is program.default
    assert program.small is not program.default


def test_without_the_options_every_run_takes_the_defaults(program, monkeypatch):
    monkeypatch.setattr(_compile, "small_run_options_apply", lambda: False)
    assert program.for_bodies(1) is program.default
    assert program.for_bodies(128, per_system=2) is program.default


def test_programs_run_once_a_call_take_the_small_run_options_when_eager(monkeypatch):
    """`once_per_call`: the input checks, a run's set-up and join, the result check take
    the small-run options whatever the batch, eagerly; under the caller's `jax.jit` they
    are part of its program (JAX refuses `compiler_options` on a nested `jit`)."""
    double = _compile.once_per_call(lambda x: 2 * x)
    program, seen = double.program, []
    for name in ("small", "default"):
        compiled = getattr(program, name)
        spy = lambda *args, compiled=compiled, name=name: seen.append(name) or compiled(*args)  # noqa: E731
        monkeypatch.setattr(program, name, spy)
    x = jnp.arange(1e5)  # a large batch: still the small-run options
    np.testing.assert_array_equal(double(x), 2 * x)
    np.testing.assert_array_equal(jax.jit(double)(x), 2 * x)
    assert seen == ["small", "default"]
    monkeypatch.setattr(_compile, "small_run_options_apply", lambda: False)
    double(x)
    assert seen[-1] == "default"


def test_input_checks_eagerly_and_under_jit():
    """The input checks (`once_per_call`) run eagerly, where bad input raises, and inside
    the caller's `jit`, where it is `RESULTS.invalid_input`."""
    body = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
    m0 = jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])

    def run(g0, m, h):
        return lievi.simulate(body, lievi.DEP(), g0, m, h=h, n_steps=2, throw=False)

    good = run(jnp.eye(4), m0, 0.1)
    assert good.result == lievi.RESULTS.successful
    assert jax.jit(run)(jnp.eye(4), m0, 0.1).result == lievi.RESULTS.successful
    bad_g0 = jnp.eye(4).at[0, 0].set(1.5)
    for g0, m, h in ((bad_g0, m0, 0.1), (jnp.eye(4), m0.at[0].set(jnp.nan), 0.1)):
        with pytest.raises(ValueError, match="g0|m0"):
            run(g0, m, h)
        assert jax.jit(run)(g0, m, h).result == lievi.RESULTS.invalid_input
    assert jax.jit(run)(jnp.eye(4), m0, -0.1).result == lievi.RESULTS.invalid_input


def test_bodies_of_a_run():
    assert _compile.bodies_of(jnp.eye(4)) == 1
    assert _compile.bodies_of(jnp.zeros((2, 4, 4))) == 2  # a system of two bodies
    assert _compile.bodies_of(jnp.zeros((5, 2, 4, 4))) == 10  # a batch of five of them


def test_bodies_per_system():
    system, _, _ = _binary()
    assert _compile.bodies_per_system(system) == 2
    batch = jax.vmap(lambda G: lievi.gravitating_bodies(G, *_shapes()))(jnp.ones(5))
    assert _compile.bodies_per_system(batch) == 2  # a batch of systems: per system
    assert _compile.bodies_per_system(lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)) == 1
    assert _compile.bodies_per_system(lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))) == 1


def _shapes():
    """The point masses and their positions of two bodies of three point masses each."""
    masses = jnp.array([[1.0, 0.6, 0.8], [0.5, 0.4, 0.3]])
    points = jnp.array(
        [
            [[0.12, 0.0, 0.0], [-0.1, 0.08, 0.0], [0.0, -0.06, 0.09]],
            [[0.1, 0.0, 0.02], [-0.08, 0.07, 0.0], [0.0, -0.05, -0.08]],
        ]
    )
    return masses, points


def _binary():
    """Two bodies of three point masses each in mutual gravity, 1.5 apart, spinning."""
    system = lievi.gravitating_bodies(1.0, *_shapes())
    g0 = jnp.tile(jnp.eye(4), (2, 1, 1)).at[:, 0, 3].set(jnp.array([-0.5, 1.0]))
    m0 = jnp.array([[0.03, 0.05, 0.1, 0.0, -1.2, 0.0], [0.04, -0.02, 0.01, 0.0, 1.2, 0.0]])
    return system, g0, m0


@pytest.mark.parametrize(
    "case",
    ["SE(3) one body, DEP kernel", "binary, DEP", "batch of binaries, DEP"],
)
def test_the_options_do_not_change_the_numbers(case, monkeypatch):
    """One run with the small-run options and the same run with XLA's defaults (the
    options then do not apply) agree to round-off: 20 steps, each saved, float64, to 64
    ulps of the largest entry of each output. (Over hundreds of steps the binary's orbit
    amplifies a different rounding, as it does any: 4e-13 after 500 steps.)"""
    run_of = lievi.simulate
    if case.startswith("SE(3)"):
        system = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
        g0, m0 = jnp.eye(4), jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])
    else:
        system, g0, m0 = _binary()
        if case.startswith("batch"):  # three binaries: six bodies a step, two a system
            m0 = m0 * jnp.array([1.0, 1.05, 0.95])[:, None, None]
            run_of = lievi.simulate_batch

    def run():
        return run_of(system, lievi.DEP(), g0, m0, h=0.05, n_steps=20)

    small = run()
    monkeypatch.setattr(_compile, "small_run_options_apply", lambda: False)
    default = run()
    assert np.all(small.result == int(lievi.RESULTS.successful))
    assert np.all(default.result == int(lievi.RESULTS.successful))
    for a, b in ((small.g, default.g), (small.m, default.m)):
        scale = float(jnp.max(jnp.abs(b)))
        np.testing.assert_allclose(a, b, rtol=0, atol=64 * np.finfo(np.float64).eps * scale)
