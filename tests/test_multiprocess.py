"""A batch over two processes on this machine (`jax.distributed`, CPU, gloo collectives):
each process holds its own half of a 64-body batch (`lievi.shard_process_batch`); the
forward run (default suite), a gradient summed over all bodies and a short fit (`-m
slow`), gathered (`lievi.gather_batch`), equal the same computations in one process to
round-off.

The processes are `tests/multiprocess_worker.py`; its functions also give the reference.
"""

import os
import pathlib
import socket
import subprocess
import sys

import multiprocess_worker as worker
import numpy as np
import pytest

WORKER = pathlib.Path(worker.__file__)
ROOT = WORKER.parent.parent
PROCESSES = 2


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _run_two_processes(tmp_path, *extra):
    """Run the worker as two processes of one `jax.distributed` run; the gathered results."""
    out = tmp_path / "gathered.npz"
    port = _free_port()
    env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}  # one device a process
    env.update(JAX_PLATFORMS="cpu", PYTHONPATH=os.pathsep.join([str(ROOT), str(WORKER.parent)]))
    command = [sys.executable, str(WORKER), "", str(PROCESSES), str(port), str(out), *extra]
    processes = [
        subprocess.Popen(
            command[:2] + [str(p)] + command[3:],
            env=env,
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
        )
        for p in range(PROCESSES)
    ]
    logs = []
    try:
        for p in processes:
            logs.append(p.communicate(timeout=600)[0])
    finally:
        for p in processes:
            p.kill()
    for p, log in enumerate(logs):
        assert f"process {p}: done" in log, log
    return dict(np.load(out))


def _check_forward(gathered, inertia, m0, h):
    g, m, result = (np.asarray(x) for x in worker.forward(inertia, m0, h))
    assert gathered["m"].shape == m.shape == (worker.BATCH, worker.N_STEPS // worker.EVERY + 1, 3)
    # Equal to round-off, not bitwise: XLA vectorises the per-process shapes differently.
    np.testing.assert_allclose(gathered["g"], g, rtol=0, atol=1e-14)
    np.testing.assert_allclose(gathered["m"], m, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(gathered["result"], result)


def test_two_processes_equal_one(tmp_path):
    """The forward run (the default suite's check that the multi-process path works)."""
    inertia, m0, h = worker.problem()
    _check_forward(_run_two_processes(tmp_path), inertia, m0, h)


@pytest.mark.slow
def test_two_processes_gradient_and_fit_equal_one(tmp_path):
    """With a gradient summed over all bodies (an all-reduce across the processes) and the
    short fit: each process fits its own rows; gathered, they equal one fit of the whole
    batch."""
    inertia, m0, h = worker.problem()
    gathered = _run_two_processes(tmp_path, "gradient", "fit")
    _check_forward(gathered, inertia, m0, h)
    grad = np.asarray(worker.gradient(inertia, m0, h))
    assert np.all(np.abs(grad) > 1e-8)  # every body contributes
    np.testing.assert_allclose(gathered["grad"], grad, rtol=1e-12, atol=0)
    params, loss = (np.asarray(x) for x in worker.fit(inertia, m0))
    assert np.all(np.abs(params - worker.GUESS) > 1e-6)  # the fit moved every body
    np.testing.assert_allclose(gathered["fit_params"], params, rtol=1e-10, atol=0)
    np.testing.assert_allclose(gathered["fit_loss"], loss, rtol=1e-8, atol=1e-20)
