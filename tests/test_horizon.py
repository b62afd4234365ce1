"""Eager runs take the horizon as traced loop bounds (`lievi/_horizon.py`): the same numbers
as the static scan (the path under `jit`), bit for bit, and a new `n_steps` or
`save_every` compiles no new step."""

import collections

import equinox as eqx
import jax
import jax.monitoring
import jax.numpy as jnp
import numpy as np
import pytest

import lievi
from lievi import _compile, _horizon, _simulate_kernel

COMPILED = collections.Counter()


def _record(name, duration, **kwargs):
    if name == "/jax/core/compile/backend_compile_duration":
        COMPILED[kwargs.get("fun_name")] += 1


jax.monitoring.register_event_duration_secs_listener(_record)


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
    monkeypatch.setattr(_horizon, "MAX_BLOCK_SAVES", 4)
    jax.clear_caches()
    yield
    jax.clear_caches()


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
def test_simulate_eager_equals_jit(
    small_blocks, monkeypatch, system, integrator, m0, n_steps, save_every
):
    # The blocks with XLA's default options, as under `jit`: one body's eager programs are
    # otherwise compiled with the small-run options (`lievi/_compile.py`), another code
    # generator, equal to round-off only (1 ulp measured; `tests/test_compile.py`).
    monkeypatch.setattr(_compile, "SMALL_RUN_BODIES", 0)
    g0 = jnp.eye(system.group.matrix_dim)
    kwargs = dict(h=0.1, n_steps=n_steps, save_every=save_every)
    eager = lievi.simulate(system, integrator, g0, m0, **kwargs)
    traced = eqx.filter_jit(lambda s, g, m: lievi.simulate(s, integrator, g, m, **kwargs))
    # The preprocessed method's per-run constants are computed in another program than
    # under `jit` (fused differently by XLA): equal to round-off; the others bit for bit.
    exact = not isinstance(integrator, lievi.PreprocessedMoserVeselov)
    _same(eager, traced(system, g0, m0), exact)


# The generic path's blocks run where a method has no kernel for the system (the
# preprocessed Moser–Veselov method); a method with one runs it on every path.
FAST_AND_GENERIC = pytest.mark.parametrize(
    "fast, integrator",
    [(True, lievi.DEP(chart="exp")), (False, lievi.PreprocessedMoserVeselov())],
    ids=["fast", "generic"],
)


@FAST_AND_GENERIC
@pytest.mark.parametrize("save", [("g", "m", "stats"), ("m",)])
@pytest.mark.parametrize("h", [0.1, 0.1 + 0.01 * jnp.arange(5.0)], ids=["shared-h", "h-per-body"])
def test_simulate_batch_eager_equals_jit(small_blocks, fast, integrator, save, h):
    assert (integrator.batch_kernel(BODY) is None) != fast
    kwargs = dict(h=h, n_steps=18, save_every=2, save=save, fast=fast)
    eager = lievi.simulate_batch(BODY, integrator, G0, MOMENTA, **kwargs)
    traced = eqx.filter_jit(lambda s, m: lievi.simulate_batch(s, integrator, G0, m, **kwargs))
    _same(eager, traced(BODY, MOMENTA), exact=False)


@FAST_AND_GENERIC
def test_failure_is_recorded_across_blocks(small_blocks, fast, integrator):
    """A failed body: its code, failed step and NaN saves in every later block, as under
    `jit`."""
    momenta = MOMENTA.at[2].set(jnp.array([0.0, 100.0, 0.0]))  # h|Ω| = 5: past the bound
    kwargs = dict(h=0.1, n_steps=12, save_every=1, throw=False, fast=fast)
    eager = lievi.simulate_batch(BODY, integrator, G0, momenta, **kwargs)
    assert eager.result[2] != lievi.RESULTS.successful
    assert np.all(np.isnan(eager.m[2, eager.stats["failed_step"][2] + 1 :]))
    traced = eqx.filter_jit(lambda m: lievi.simulate_batch(BODY, integrator, G0, m, **kwargs))
    _same(eager, traced(momenta), exact=False)


@pytest.mark.parametrize(
    "fast, integrator",
    [(True, lievi.DEP(chart="cayley")), (False, lievi.PreprocessedMoserVeselov())],
    ids=["fast", "generic"],
)
def test_new_horizon_compiles_no_new_step(fast, integrator):
    """The step's program (`_block`) is compiled once for all horizons; what a new horizon
    compiles is only the join of the blocks."""
    jax.clear_caches()
    runs = [
        lambda n, k: lievi.simulate(BODY, integrator, G0, M0, h=0.1, n_steps=n, save_every=k),
        lambda n, k: lievi.simulate_batch(
            BODY, integrator, G0, MOMENTA, h=0.1, n_steps=n, save_every=k, fast=fast
        ),
    ]
    for run in runs:
        run(6, 1)
        COMPILED.clear()
        for n_steps, save_every in ((8, 1), (8, 2), (30, 5)):
            jax.block_until_ready(run(n_steps, save_every))
        assert COMPILED["jit(_block)"] == 0, COMPILED
        assert sum(COMPILED.values()) > 0  # the listener sees compiles (the joins)


def test_progress_meter_of_an_eager_run(small_blocks, capsys):
    """0 % first and 100 % last, on one line, over several blocks."""
    meter = lievi.TextProgressMeter(delay=0.0)
    lievi.simulate(BODY, lievi.DEP(), G0, M0, h=0.1, n_steps=40, progress_meter=meter)
    jax.effects_barrier()
    out = capsys.readouterr().out
    values = [float(x) for x in out.replace("%", " ").split() if x.replace(".", "").isdigit()]
    assert values[0] == 0.0 and values[-1] == 100.0 and np.all(np.diff(values) > 0)
    assert out.count("\n") == 1


def test_under_transformations_the_static_scan_is_used():
    """`jit`, `grad` and `vmap` trace the run: the static scan (reverse mode needs it)."""
    assert _horizon.horizon_traced(M0)
    seen = []
    jax.jit(lambda m: seen.append(_horizon.horizon_traced(m)) or m)(M0)
    jax.grad(lambda h: seen.append(_horizon.horizon_traced(M0)) or h)(0.1)
    assert seen == [False, False]

    def final_energy(h):
        sol = lievi.simulate(BODY, lievi.DEP(), G0, M0, h=h, n_steps=6)
        return BODY.energy(sol.m[-1])

    assert np.isfinite(jax.grad(final_energy)(0.1))


def _kernels_of_blocks(monkeypatch):
    """The `max_steps` of the kernel of each block an eager run calls (`_block`)."""
    seen = []
    block = _simulate_kernel._block

    class Spy:
        def for_bodies(self, n):
            program = block.for_bodies(n)

            def spy(kernel, *args):
                inner = getattr(kernel, "inner", kernel)  # a composition's stages
                seen.append(inner.max_steps)
                return program(kernel, *args)

            return spy

    monkeypatch.setattr(_simulate_kernel, "_block", Spy())
    # No run before this test has left a kernel marked as needing its loop.
    monkeypatch.setattr(_simulate_kernel, "_NEEDED_LOOP", set())
    return seen


@pytest.mark.parametrize(
    "m0, h, fails",
    [
        (M0, 0.1, False),  # the fixed iterations converge at every step
        (M0 * 10, 0.3, True),  # they do not: the Newton loop finishes the steps
    ],
    ids=["fixed-iterations-suffice", "loop-needed"],
)
def test_one_body_tries_the_fixed_iterations_first(small_blocks, monkeypatch, m0, h, fails):
    """An eager run of one body first runs the kernel without its Newton loop
    (`fixed_iterations_only`, compiled sooner); from the first block where that fails a
    step, the whole kernel runs, that block again included. Either way the run is the one
    under `jit` (the whole kernel throughout), to round-off, and every step succeeds: bit
    for bit or a few ulps where the steps are easy, within the Newton tolerance's reach
    (1e-12 relative; the tolerance is 64 ulps of the residual, and two programs that round
    differently may stop an iteration apart) where they need the loop."""
    integrator = lievi.DEP()
    fixed = integrator.batch_kernel(BODY).fixed_iterations_only().max_steps
    assert fixed < integrator.max_steps
    seen = _kernels_of_blocks(monkeypatch)
    kwargs = dict(h=h, n_steps=12, save_every=1)
    eager = lievi.simulate(BODY, integrator, G0, m0, **kwargs)
    assert eager.result == lievi.RESULTS.successful
    # 12 saves in blocks of 4: three blocks, the first run twice where the loop is needed.
    expected = [fixed, *[integrator.max_steps] * 3] if fails else [fixed] * 3
    assert seen == expected
    traced = eqx.filter_jit(lambda m: lievi.simulate(BODY, integrator, G0, m, **kwargs))(m0)
    if not fails:
        _same(eager, traced, exact=False)
        return
    np.testing.assert_array_equal(eager.result, traced.result)
    for x, y in ((eager.g, traced.g), (eager.m, traced.m)):
        np.testing.assert_allclose(x, y, rtol=0, atol=1e-12 * np.abs(np.asarray(y)).max())


def test_small_batches_try_the_fixed_iterations_first(small_blocks, monkeypatch):
    """A batch of up to `FIXED_FIRST_MAX_BODIES` bodies takes the same rule as one body: the
    kernel without its loop while every body's steps succeed, the whole kernel from the
    first block where one body's do not (here the third body's, whose `h|Π|` is ten times
    the others'), and in the later runs of that kernel on the same shapes. Every run is
    the one under `jit`, as for one body."""
    seen = _kernels_of_blocks(monkeypatch)
    integrator = lievi.DEP()
    fixed = integrator.batch_kernel(BODY).fixed_iterations_only().max_steps
    kwargs = dict(h=0.3, n_steps=12, save_every=1)
    traced = eqx.filter_jit(lambda m: lievi.simulate_batch(BODY, integrator, G0, m, **kwargs))
    whole = [integrator.max_steps] * 3
    # After the run that needed the loop, the same kernel on the same shapes runs whole
    # from the start: its program is compiled, and the light one would fail a block again.
    hard = MOMENTA.at[2].multiply(10.0)
    cases = (
        (MOMENTA, [fixed] * 3, False),
        (hard, [fixed, *whole], True),
        (hard, whole, True),
        (MOMENTA, whole, False),
    )
    for momenta, blocks, fails in cases:
        seen.clear()
        eager = lievi.simulate_batch(BODY, integrator, G0, momenta, **kwargs)
        np.testing.assert_array_equal(eager.result, lievi.RESULTS.successful)
        assert seen == blocks
        expected = traced(momenta)
        np.testing.assert_array_equal(eager.result, expected.result)
        for x, y in ((eager.g, expected.g), (eager.m, expected.m)):
            scale = np.abs(np.asarray(y)).max()
            np.testing.assert_allclose(x, y, rtol=0, atol=(1e-12 if fails else 64e-16) * scale)


def test_a_body_that_came_in_failed_does_not_count():
    """The host test after a tried block (`_no_new_failure`) asks for no *new* failure: a
    body already failed at the block's start stays failed in the whole kernel too, and
    must not make the run compile it."""
    ok, bad = int(lievi.RESULTS.successful), int(lievi.RESULTS.nonfinite)

    def state(*results):
        return (None, None, np.array(results, np.int32))

    assert _simulate_kernel._no_new_failure(state(ok, bad), state(ok, bad))
    assert not _simulate_kernel._no_new_failure(state(ok, ok), state(ok, bad))
    assert not _simulate_kernel._no_new_failure(state(ok, bad), state(bad, bad))


def test_large_batches_and_meters_run_the_whole_kernel(small_blocks, monkeypatch):
    """A batch of more than `FIXED_FIRST_MAX_BODIES` bodies (the more bodies, the likelier
    that trying first compiles twice) and a run with a progress meter (a block run again
    would report its steps twice) take the whole kernel from the start."""
    monkeypatch.setattr(_simulate_kernel, "FIXED_FIRST_MAX_BODIES", 1)
    seen = _kernels_of_blocks(monkeypatch)
    integrator = lievi.DEP()
    lievi.simulate_batch(BODY, integrator, G0, MOMENTA[:2], h=0.1, n_steps=4)
    meter = lievi.TextProgressMeter(delay=0.0)
    lievi.simulate(BODY, integrator, G0, M0, h=0.1, n_steps=4, progress_meter=meter)
    assert seen == [integrator.max_steps] * 2
