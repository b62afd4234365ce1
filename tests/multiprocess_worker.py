"""One process of the two-process test (tests/test_multiprocess.py), and the computations
it shares with the single-process reference.

Run as `python multiprocess_worker.py PROCESS COUNT PORT OUT [gradient] [fit]`: joins a
`jax.distributed` run of COUNT processes whose coordinator listens on 127.0.0.1:PORT, takes
its own share of a 64-body batch, runs a forward batch (and with `gradient`, a gradient;
with `fit`, a short fit), and process 0 writes the gathered results to OUT (`.npz`).
"""

import sys

import jax
import jax.numpy as jnp
import numpy as np

BATCH = 64
H, N_STEPS, EVERY = 0.1, 20, 5
GUESS = np.array([1.5, 1.2, 1.0])


def problem():
    """The whole batch (NumPy): principal moments, momenta, step sizes."""
    rng = np.random.default_rng(0)
    inertia = rng.uniform(0.5, 2.0, (BATCH, 3))
    m0 = rng.normal(size=(BATCH, 3))
    h = rng.uniform(0.05, 0.2, BATCH)
    return inertia, m0, h


def share(x, process: int, count: int):
    """Process `process`'s rows of `x` (contiguous, in process order)."""
    rows = len(x) // count
    return x[process * rows : (process + 1) * rows]


def forward(inertia, m0, h):
    """`(g, m, result)` of a fast-path batch run (DEP), every 5th step saved."""
    import lievi

    bodies = jax.vmap(lievi.RigidBody)(inertia)
    g0 = jnp.broadcast_to(jnp.eye(3), (m0.shape[0], 3, 3))
    sol = lievi.simulate_batch(
        bodies,
        lievi.DEP(),
        g0,
        m0,
        h=h,
        n_steps=N_STEPS,
        save=lievi.Save(every=EVERY),
        system_axis=0,
    )
    return sol.g, sol.m, sol.result


@jax.jit
def gradient(inertia, m0, h):
    """The gradient in the moments of a loss summed over the whole batch (a reduction
    across processes): the final momenta's components, weighted (not `|Π|²`, a Casimir,
    whose gradient is zero)."""

    def loss(inertia):
        return jnp.sum(forward(inertia, m0, h)[1][:, -1] * jnp.array([1.0, 2.0, 3.0]))

    return jax.grad(loss)(inertia)


def fit(inertia, m0):
    """A short fit of the moments (10 L-BFGS iterations, from one guess shared by all
    bodies) to each body's own orientations (step `H`), `Π₀` and `g₀` known. The bodies' fits are independent: each process fits its rows."""
    import lievi

    observed = forward(inertia, m0, H)[0]
    result = lievi.fit_system(
        lievi.RigidBody(jnp.asarray(GUESS)),
        observed,
        h=H,
        sample_every=EVERY,
        m0=m0,
        g0=jnp.broadcast_to(jnp.eye(3), (m0.shape[0], 3, 3)),
        max_iters=10,
    )
    return result.params, result.loss


def main(process: int, count: int, port: int, out: str, extra: list[str]) -> None:
    jax.config.update("jax_enable_x64", True)
    jax.distributed.initialize(f"127.0.0.1:{port}", num_processes=count, process_id=process)
    import lievi

    mine = [share(x, process, count) for x in problem()]
    inertia, m0, h = lievi.shard_process_batch(mine)
    assert inertia.shape == (BATCH, 3) and not inertia.is_fully_addressable
    g, m, result = forward(inertia, m0, h)
    # This process's rows are its own bodies, read without communication.
    np.testing.assert_array_equal(
        lievi.process_rows(m), share(lievi.gather_batch(m), process, count)
    )
    outputs = dict(g=g, m=m, result=result)
    if "gradient" in extra:
        outputs["grad"] = gradient(inertia, m0, h)
    if "fit" in extra:
        # The fit runs on each process's own rows; its per-body results are then gathered.
        outputs["fit_params"], outputs["fit_loss"] = lievi.shard_process_batch(
            fit(mine[0], mine[1])
        )
    gathered = lievi.gather_batch(outputs)
    if process == 0:
        np.savez(out, **gathered)
    print(f"process {process}: done", flush=True)


if __name__ == "__main__":
    main(int(sys.argv[1]), int(sys.argv[2]), int(sys.argv[3]), sys.argv[4], sys.argv[5:])
