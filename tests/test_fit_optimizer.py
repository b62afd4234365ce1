"""The batched optimiser of `fit_system` (`lievi._identification._optimizer`): one evaluation per body
per tick.

Checks (float64): L-BFGS reaches ‖∇f‖_∞ ≤ 1e-10 on the Rosenbrock function from several
starting points in one batch, each body's iterates equal to its run alone (no body's line
search affects another's); near a minimum where the decrease of `f` is below its round-off
(`f = 10⁶ + ½xᵀAx`) it still reaches ‖∇f‖ ≤ 1e-9; a function that is not finite anywhere but at the
start stalls and says so; the optax machine (Adam) takes one evaluation per iteration.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

from lievi._identification._optimizer import LBFGS, OptaxMachine


@functools.partial(jax.jit, static_argnums=(0, 1, 3, 4))
def minimise(machine, fun, x0, ticks, gtol):
    """Drive `machine` for `ticks` ticks on a batch; returns the state, evaluations and
    iterations per body."""
    value_and_grad = jax.vmap(jax.value_and_grad(fun))

    def tick(carry, _):
        state, finished, evals, iters = carry
        f, g = value_and_grad(jax.vmap(machine.trial)(state))
        told, accepted = jax.vmap(machine.tell)(state, f, g)
        iterated = accepted & ~state.fresh
        done = accepted & (jnp.max(jnp.abs(g), axis=-1) <= gtol)
        advanced = jax.vmap(machine.advance)(told)
        step = accepted & ~done
        new = jax.tree.map(
            lambda a, t: jnp.where(step.reshape((-1,) + (1,) * (a.ndim - 1)), a, t),
            advanced,
            told,
        )
        keep = lambda n, o: jnp.where(finished.reshape((-1,) + (1,) * (n.ndim - 1)), o, n)
        new = jax.tree.map(keep, new, state)
        return (
            new,
            finished | done | new.stalled,
            evals + ~finished,
            iters + (iterated & ~finished),
        ), None

    b = x0.shape[0]
    state = jax.vmap(machine.init)(x0)
    zeros = jnp.zeros(b, jnp.int32)
    carry = (state, jnp.zeros(b, bool), zeros, zeros)
    (state, finished, evals, iters), _ = jax.lax.scan(tick, carry, None, length=ticks)
    return state, finished, evals, iters


def rosenbrock(x):
    return (1 - x[0]) ** 2 + 100 * (x[1] - x[0] ** 2) ** 2


STARTS = jnp.array([[-1.2, 1.0], [0.0, 0.0], [2.0, 2.0], [-0.5, 3.0], [1.5, -1.0]])


@pytest.mark.extended  # 14 s
def test_lbfgs_rosenbrock_batch_equals_alone():
    machine = LBFGS()
    state, finished, evals, iters = minimise(machine, rosenbrock, STARTS, 400, 1e-10)
    assert np.all(np.asarray(finished)) and not np.any(np.asarray(state.stalled))
    np.testing.assert_allclose(np.asarray(state.x), 1.0, atol=1e-9)
    grads = jax.vmap(jax.grad(rosenbrock))(state.x)
    assert float(jnp.max(jnp.abs(grads))) <= 1e-10
    # Bodies finish at different ticks, each with a few evaluations per iteration at most.
    assert len(set(np.asarray(evals).tolist())) > 1
    assert np.all(np.asarray(evals) <= 3 * np.asarray(iters) + 2)
    for b in range(STARTS.shape[0]):
        alone, _, evals_b, iters_b = minimise(machine, rosenbrock, STARTS[b : b + 1], 400, 1e-10)
        assert int(evals_b[0]) == int(evals[b]) and int(iters_b[0]) == int(iters[b])
        np.testing.assert_allclose(np.asarray(alone.x[0]), np.asarray(state.x[b]), rtol=1e-13)


def test_lbfgs_converges_below_the_round_off_of_f():
    """`f = 10⁶ + ½xᵀAx`: a decrease below ε·10⁶ ≈ 2e-10 is invisible in `f` (the last
    iterations compare equal values); the iteration still goes on to ‖∇f‖ ≤ 1e-9 without
    stalling."""
    A = jnp.diag(jnp.array([1.0, 10.0, 100.0]))
    fun = lambda x: 1e6 + 0.5 * x @ A @ x
    x0 = jnp.array([[1.0, 1.0, 1.0], [-3.0, 0.5, 0.01]])
    state, finished, _, _ = minimise(LBFGS(), fun, x0, 200, 1e-9)
    assert np.all(np.asarray(finished)) and not np.any(np.asarray(state.stalled))
    assert float(jnp.max(jnp.abs(state.x @ A))) <= 1e-9


def test_lbfgs_stalls_where_no_lower_value_exists():
    """Finite only at the start: every trial is rejected; without a curvature memory the
    search gives up after `max_backtracks` evaluations and reports `stalled` (never a
    non-finite point)."""
    x0 = jnp.array([[0.3, -0.2]])
    fun = lambda x: jnp.where(jnp.all(x == x0[0]), 0.0, jnp.nan) + jnp.sum(x)
    machine = LBFGS(max_backtracks=8)
    state, finished, evals, iters = minimise(machine, fun, x0, 50, 1e-12)
    assert bool(state.stalled[0]) and bool(finished[0])
    assert int(iters[0]) == 0 and int(evals[0]) == 1 + 8
    np.testing.assert_array_equal(np.asarray(state.x), np.asarray(x0))


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64])
def test_optax_machine_one_evaluation_per_iteration(dtype):
    A = jnp.diag(jnp.array([1.0, 4.0], dtype))
    fun = lambda x: 0.5 * x @ A @ x
    x0 = jnp.array([[1.0, -1.0], [0.5, 2.0]], dtype)
    state, finished, evals, iters = minimise(OptaxMachine(optax.adam(0.05)), fun, x0, 2000, 1e-3)
    assert np.all(np.asarray(finished))
    assert state.x.dtype == dtype
    np.testing.assert_array_equal(np.asarray(evals), np.asarray(iters) + 1)
    assert float(jnp.max(jnp.abs(state.x @ A))) <= 1e-3
