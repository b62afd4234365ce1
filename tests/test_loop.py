"""The one step loop (`lievi/_loop.py`): an eager call compiles at most two programs and a
new `n_steps`, `save_every`, `h`, `t0` or new values of the inputs compile nothing; the
eager blocks give the numbers of the static scan (the path under `jit`) to round-off."""

import collections

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from helpers import GenericPreprocessed, programs_compiled
from lievi import _loop
from lievi._checks import tracing


def _same(a, b, exact=True):
    """Equal pytrees: the same structure, shapes, dtypes and values (NaN where NaN), bit for
    bit, or with `exact=False` to round-off (a few ulps: the eager run is other programs
    than the one under `jit`, which XLA may fuse differently)."""
    assert jax.tree.structure(a) == jax.tree.structure(b)
    for x, y in zip(jax.tree.leaves(a), jax.tree.leaves(b)):
        assert x.shape == y.shape and x.dtype == y.dtype
        if exact or not jnp.issubdtype(x.dtype, jnp.floating):
            np.testing.assert_array_equal(x, y)
        else:
            eps = np.finfo(x.dtype).eps
            np.testing.assert_allclose(x, y, rtol=16 * eps, atol=4 * eps)


BODY = lievi.RigidBody(jnp.array([1.0, 2.0, 3.0]))
SE3_BODY = lievi.RigidBodySE3(jnp.array([1.0, 2.0, 3.0]), 2.0)
G0, M0 = jnp.eye(3), jnp.array([0.3, -0.2, 0.5])
SE3_M0 = jnp.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])
MOMENTA = M0 * (1 + 0.1 * jax.random.normal(jax.random.PRNGKey(0), (5, 3)))


@pytest.fixture
def small_blocks(monkeypatch):
    """Blocks of 4 saves: a run of a few saves then spans several blocks and a partial one."""
    monkeypatch.setattr(_loop, "MAX_BLOCK_SAVES", 4)
    jax.clear_caches()
    yield
    jax.clear_caches()


@pytest.mark.extended  # 8–14 s each
@pytest.mark.parametrize("n_steps, save_every", [(9, 1), (12, 3), (5, 5)])
@pytest.mark.parametrize(
    "system, integrator, m0",
    [
        (BODY, lievi.DEP(chart="exp"), M0),
        (BODY, lievi.PreprocessedMoserVeselov(), M0),  # per-run state (`init`)
        (SE3_BODY, lievi.RK4(), SE3_M0),
    ],
    ids=["DEP", "preprocessed", "SE3-RK4"],
)
def test_simulate_eager_equals_jit(small_blocks, system, integrator, m0, n_steps, save_every):
    g0 = jnp.eye(system.group.matrix_dim)
    kwargs = dict(h=0.1, n_steps=n_steps, save=lievi.Save(every=save_every))
    eager = lievi.simulate(system, integrator, g0, m0, **kwargs)
    traced = eqx.filter_jit(lambda s, g, m: lievi.simulate(s, integrator, g, m, **kwargs))
    # The blocks are another program than the scan under `jit` (fused differently by XLA):
    # equal to round-off.
    _same(eager, traced(system, g0, m0), exact=False)


# The generic path's blocks run where a method has no kernel for the system (a subclass
# of the preprocessed Moser–Veselov method, with its per-run state); a method with one
# runs it on every path.
FAST_AND_GENERIC = pytest.mark.parametrize(
    "fast, integrator",
    [(True, lievi.DEP(chart="exp")), (False, GenericPreprocessed())],
    ids=["fast", "generic"],
)


@pytest.mark.extended  # 9–14 s each
@FAST_AND_GENERIC
@pytest.mark.parametrize(
    "save", [lievi.Save(every=2), lievi.Save(g=False, stats=False, every=2)], ids=["all", "m"]
)
@pytest.mark.parametrize("h", [0.1, 0.1 + 0.01 * jnp.arange(5.0)], ids=["shared-h", "h-per-body"])
def test_simulate_batch_eager_equals_jit(small_blocks, fast, integrator, save, h):
    assert (integrator.batch_kernel(BODY) is None) != fast
    kwargs = dict(h=h, n_steps=18, save=save, tuning=lievi.advanced.Tuning(fast=fast))
    eager = lievi.simulate_batch(BODY, integrator, G0, MOMENTA, **kwargs)
    traced = eqx.filter_jit(lambda s, m: lievi.simulate_batch(s, integrator, G0, m, **kwargs))
    _same(eager, traced(BODY, MOMENTA), exact=False)


@pytest.mark.extended  # 10–11 s each
@FAST_AND_GENERIC
def test_failure_is_recorded_across_blocks(small_blocks, fast, integrator):
    """A failed body: its code, failed step and NaN saves in every later block, as under
    `jit`."""
    momenta = MOMENTA.at[2].set(jnp.array([0.0, 100.0, 0.0]))  # h|Ω| = 5: past the bound
    kwargs = dict(
        h=0.1, n_steps=12, save=lievi.Save(), tuning=lievi.advanced.Tuning(fast=fast), throw=False
    )
    eager = lievi.simulate_batch(BODY, integrator, G0, momenta, **kwargs)
    assert eager.result[2] != lievi.RESULTS.successful
    assert np.all(np.isnan(eager.m[2, eager.stats["failed_step"][2] + 1 :]))
    traced = eqx.filter_jit(lambda m: lievi.simulate_batch(BODY, integrator, G0, m, **kwargs))(
        momenta
    )
    # The failed step's residual is that of a Newton iteration that diverged for its
    # `max_steps` iterations (about 1e2 here): the two programs' round-off grows through
    # them (45 ulps measured), so that one entry is compared to 1e-12 relative, the rest
    # to round-off.
    step = int(eager.stats["failed_step"][2])
    np.testing.assert_allclose(
        eager.stats["residual"][2, step], traced.stats["residual"][2, step], rtol=1e-12
    )
    residual = traced.stats["residual"].at[2, step].set(eager.stats["residual"][2, step])
    _same(eager, eqx.tree_at(lambda s: s.stats["residual"], traced, residual), exact=False)


@pytest.mark.parametrize(
    "fast, integrator",
    [(True, lievi.DEP(chart="cayley")), (False, GenericPreprocessed())],
    ids=["fast", "generic"],
)
def test_an_eager_call_compiles_two_programs_and_a_new_horizon_none(fast, integrator):
    """The run's set-up with its input checks, and its block of saves: two programs, for
    every horizon, step size, start time and value of the inputs (counts of compilations,
    not timings)."""
    jax.clear_caches()
    body = lievi.RigidBody(jnp.array([1.0, 2.0, 3.1]))  # values no other test compiled
    one = lambda n, k, h, t0, m, b: lievi.simulate(  # noqa: E731
        b, integrator, G0, m, h=h, n_steps=n, save=lievi.Save(every=k), t0=t0
    )
    many = (
        lambda n, k, h, t0, m, b: lievi.simulate_batch(  # noqa: E731
            b,
            integrator,
            G0,
            m[:1] * np.asarray(MOMENTA),
            h=h,
            n_steps=n,
            save=lievi.Save(every=k),
            tuning=lievi.advanced.Tuning(fast=fast),
        )
    )
    # NumPy inputs: the test's own arithmetic compiles nothing.
    m1, m2 = np.asarray(M0), np.asarray(M0) * 1.5
    other = lievi.RigidBody(np.array([1.5, 2.0, 3.0]))
    for run in (one, many):
        compiled = programs_compiled(lambda: run(6, 1, 0.1, 0.0, m1, body))
        assert len(compiled) <= 2, compiled
        for args in ((8, 1, 0.1, 0.0), (8, 2, 0.05, 1.0), (30, 5, 0.2, -2.0), (700, 1, 0.1, 0.0)):
            compiled = programs_compiled(lambda: run(*args, m2, other))
            assert len(compiled) == 0, (args, compiled)


def test_a_gradient_of_an_eager_call_compiles_its_two_programs_only():
    """Under `jax.vjp` without an outer `jit` the run is traced: its forward and backward
    programs, and nothing else, also with `throw=True` (the failure check is part of the
    run's program; applied after it, each of its operations was a program of its own)."""
    jax.clear_caches()
    body = lievi.RigidBody(np.array([1.0, 2.0, 3.2]))  # values no other test compiled
    m0 = np.asarray(MOMENTA[:2])

    def final_momenta(m):
        save = lievi.Save(g=False, stats=False, every=2)
        return lievi.simulate_batch(body, lievi.RK4(), G0, m, h=0.1, n_steps=2, save=save).m

    cotangents = []

    def gradient():  # run once, its cotangent kept for the check below
        momenta, pullback = jax.vjp(final_momenta, m0)  # no arithmetic of the test's own
        cotangents.append(pullback(np.ones(momenta.shape))[0])
        return cotangents[-1]

    compiled = programs_compiled(gradient)
    assert collections.Counter(compiled) == {"jit(_static_program)": 2}, compiled
    (cotangent,) = cotangents
    assert cotangent.shape == m0.shape and np.all(np.isfinite(cotangent))


def test_progress_meter_of_an_eager_run(small_blocks, capsys):
    """0 % first and 100 % last, on one line, over several blocks."""
    meter = lievi.TextProgressMeter(delay=0.0)
    lievi.simulate(BODY, lievi.DEP(), G0, M0, h=0.1, n_steps=40, progress_meter=meter)
    jax.effects_barrier()
    out = capsys.readouterr().out
    values = [float(x) for x in out.replace("%", " ").split() if x.replace(".", "").isdigit()]
    assert values[0] == 0.0 and values[-1] == 100.0 and np.all(np.diff(values) > 0)
    assert out.count("\n") == 1


def test_an_eager_trajectory_fills_its_final_layout(small_blocks):
    """The blocks' saves (4 a block, the last one partial) land in one batch-major
    trajectory, the initial save in front, in the order of the steps: each save equal to
    a run stopped there; and the host array a trajectory is filled in lies on a 64-byte
    boundary, where JAX takes it without a copy (on the CPU)."""
    kwargs = dict(h=0.1, save=lievi.Save(every=2), throw=True)
    whole = lievi.simulate_batch(BODY, lievi.DEP(), G0, MOMENTA, n_steps=22, **kwargs)
    assert whole.g.shape == (5, 12, 3, 3) and whole.stats["residual"].shape == (5, 11)
    np.testing.assert_array_equal(whole.g[:, 0], np.broadcast_to(G0, (5, 3, 3)))
    for n_steps in (2, 10, 18):  # the first save of blocks 1, 2 and 3
        part = lievi.simulate_batch(BODY, lievi.DEP(), G0, MOMENTA, n_steps=n_steps, **kwargs)
        np.testing.assert_array_equal(whole.m[:, : n_steps // 2 + 1], part.m)
        np.testing.assert_array_equal(
            whole.stats["residual"][:, : n_steps // 2], part.stats["residual"]
        )
    host = _loop._host_empty((5, 12, 3, 3), np.float64)
    assert host.ctypes.data % 64 == 0 and host.flags.c_contiguous
    if jax.default_backend() == "cpu":
        taken = jax.device_put(host, may_alias=True)
        assert taken.unsafe_buffer_pointer() == host.ctypes.data


@pytest.mark.extended  # 13 s
def test_under_transformations_the_static_scan_is_used():
    """`jit`, `grad` and `vmap` trace the run: the static scan (reverse mode needs it)."""
    assert not tracing()
    seen = []
    jax.jit(lambda m: seen.append(tracing()) or m)(M0)
    jax.grad(lambda h: seen.append(tracing()) or h)(0.1)
    assert seen == [True, True]

    def final_energy(h):
        sol = lievi.simulate(BODY, lievi.DEP(), G0, M0, h=h, n_steps=6)
        return BODY.energy(sol.m[-1])

    assert np.isfinite(jax.grad(final_energy)(0.1))


def _close_encounter():
    """Two bodies of one point mass each in mutual gravity passing within 0.02 of each
    other at a step far too large for it: finite numbers, every step "successful"
    without a monitor, and an energy error of many times the energy."""
    points = jnp.zeros((2, 1, 3))
    bodies = lievi.gravitating_bodies(
        1.0, jnp.ones((2, 1)), points, extra_inertia=jnp.tile(0.1 * jnp.eye(3), (2, 1, 1))
    )
    g0 = jnp.tile(jnp.eye(4), (2, 1, 1)).at[:, 0, 3].set(jnp.array([-1.0, 1.0]))
    g0 = g0.at[:, 1, 3].set(jnp.array([-0.01, 0.01]))
    m0 = jnp.array([[0.0, 0.0, 0.0, 1.0, 0.0, 0.0], [0.0, 0.0, 0.0, -1.0, 0.0, 0.0]])
    return bodies, g0, m0


@pytest.mark.parametrize("batched", [False, True], ids=["simulate", "simulate_batch"])
def test_invariant_monitor_reports_a_drift(batched):
    """With `EnergyMonitor` a run whose energy drifts past the tolerance ends with
    `RESULTS.invariant_drift` at the save that saw it (NaN from there on); without it the
    same run reports success. A monitor on a run that keeps its energy changes nothing."""
    bodies, g0, m0 = _close_encounter()
    kwargs = dict(h=0.05, n_steps=40, save=lievi.Save(), throw=False)
    if batched:
        run = lambda monitor, m, g=g0: lievi.simulate_batch(  # noqa: E731
            bodies, lievi.LiePoissonSplitting(), g, m[None], monitor=monitor, **kwargs
        )
    else:
        run = lambda monitor, m, g=g0: jax.tree.map(  # noqa: E731
            lambda x: x[None],
            lievi.simulate(bodies, lievi.LiePoissonSplitting(), g, m, monitor=monitor, **kwargs),
        )
    plain = run(None, m0)
    energies = lievi.diagnostics.energy(bodies, plain.g[0], plain.m[0])
    assert int(plain.result[0]) == lievi.RESULTS.successful
    assert np.max(np.abs(energies - energies[0])) > 10 * abs(energies[0])  # it went wrong
    watched = run(lievi.EnergyMonitor(rtol=1e-2), m0)
    assert int(watched.result[0]) == lievi.RESULTS.invariant_drift
    step = int(watched.stats["failed_step"][0])
    drift = np.abs(energies - energies[0]) / abs(energies[0])
    # The first save past the tolerance is the one after the failed step.
    assert drift[step + 1] > 1e-2 and np.all(drift[: step + 1] <= 1e-2)
    assert np.all(np.isnan(watched.m[0, step + 1 :]))
    np.testing.assert_array_equal(watched.m[0, : step + 1], plain.m[0, : step + 1])
    # Far apart (they fall towards each other for a fraction of the time to meet), the
    # energy is kept and the monitor never fires.
    far = g0.at[:, 0, 3].set(jnp.array([-5.0, 5.0]))
    assert int(run(lievi.EnergyMonitor(rtol=1e-2), 0 * m0, far).result[0]) == 0


def test_monitor_must_be_a_monitor():
    with pytest.raises(ValueError, match="`monitor` must be None or an invariant monitor"):
        lievi.simulate(BODY, lievi.DEP(), G0, M0, h=0.1, n_steps=2, monitor="energy")
    with pytest.raises(ValueError, match="`rtol` must be > 0"):
        lievi.EnergyMonitor(rtol=-1.0)


def test_deprecated_names_warn():
    with pytest.warns(DeprecationWarning, match="lievi.SystemFit"):
        assert lievi.InertiaFit is lievi.SystemFit
    assert "InertiaFit" not in lievi.__all__
