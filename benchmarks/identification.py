"""Batched identification at scale: `fit_inertia` over many bodies in one call.

The test problem of `tests/test_identification.py::test_thousand_bodies_in_one_call`:
random realisable bodies with unit momenta, T = 20, h = 0.05, 41 orientation samples with
1 % noise on the rotation vectors, maximum-likelihood weights, Π₀ and g₀ unknown, one poor
initial guess for every body. Reports the wall time of the whole fit (compilations
included) and split into its parts, the loss evaluations (ticks) and the iterations per
body, and the accuracy; as baselines in the same run, the cost of one batched forward run
and one batched gradient of the same loss (so the fit's cost reads as a number of gradient
evaluations).

    python benchmarks/identification.py                # 1000 bodies
    python benchmarks/identification.py --bodies 128

Writes `benchmarks/results/identification.json`.

    python benchmarks/identification.py --default-start

The default start instead (`tests/test_identification.py::test_default_start_sparse_noisy`):
64 torque-free bodies observed from the identity, T = 10, 41 attitude samples
(Δt = 0.25) with σ = 0.01 rad of noise on each axis, fitted with h = 0.05,
`sample_every=5`, unit weights and no initial guess (`inertia=None`: the linear
least-squares estimate). Reports the converged count, the errors of the normalised
moments, and each body's final loss against the loss of the true parameters on the same
data (a fit at or below it is as good as the truth can be: what error remains is the
noise's). Writes `benchmarks/results/identification_default_start.json`.
"""

from __future__ import annotations

import argparse
import json
import os
import platform
import time
from pathlib import Path

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
import lievi._identification._schedule as schedule  # noqa: E402
from lievi import SO3  # noqa: E402

H, N_STEPS, EVERY, NOISE = 0.05, 400, 10, 0.01
GUESS = jnp.array([1.5, 1.2, 1.0])


def orientations(inertias, momenta, save=None, **kwargs):
    """The sampled orientations of the model, every body from the identity."""
    n = inertias.shape[0]
    save = lievi.Save(every=EVERY) if save is None else save
    return lievi.simulate_batch(
        jax.vmap(lievi.RigidBody)(inertias),
        lievi.DEP(),
        jnp.broadcast_to(jnp.eye(3), (n, 3, 3)),
        momenta,
        h=H,
        n_steps=N_STEPS,
        save=save,
        system_axis=0,
        **kwargs,
    ).g


def problem(n, seed=2):
    rng = np.random.default_rng(seed)
    Lambda = rng.uniform(0.2, 1.5, size=(n, 3))
    inertias = jnp.asarray(Lambda.sum(-1, keepdims=True) - Lambda)
    m0 = rng.normal(size=(n, 3))
    momenta = jnp.asarray(m0 / np.linalg.norm(m0, axis=-1, keepdims=True))
    clean = orientations(inertias, momenta)
    r = np.asarray(SO3.log(clean))
    r = r + NOISE * np.linalg.norm(r, axis=-1, keepdims=True) * rng.normal(size=r.shape)
    observed = SO3.exp(jnp.asarray(r))
    w = 1 / (np.sum(r**2, axis=-1) + 0.1**2)
    weights = jnp.asarray(w / w.mean(axis=-1, keepdims=True))
    return inertias, momenta, observed, weights


def baseline(inertias, momenta, observed):
    """Seconds of one batched forward run and one batched gradient of the orientation loss."""

    def loss(I):
        g = orientations(
            I, momenta, save=lievi.Save(m=False, stats=False, every=EVERY), throw=False
        )
        return jnp.sum((g - observed) ** 2)

    out = {}
    for name, fn in (("forward", jax.jit(loss)), ("gradient", jax.jit(jax.grad(loss)))):
        jax.block_until_ready(fn(inertias * 1.01))
        t = time.perf_counter()
        for _ in range(5):
            jax.block_until_ready(fn(inertias * 1.01))
        out[name] = (time.perf_counter() - t) / 5
    return out


def default_start_problem(n=64, seed=0, sigma=0.01, h=0.05, every=5, n_steps=200):
    """Torque-free bodies from the identity, attitude noise `SO3.exp(σ ε)`, ε ~ N(0, I₃)."""
    rng = np.random.default_rng(seed)
    Lambda = rng.uniform(0.2, 1.5, size=(n, 3))
    inertias = jnp.asarray(Lambda.sum(-1, keepdims=True) - Lambda)
    m0 = rng.normal(size=(n, 3))
    momenta = jnp.asarray(m0 / np.linalg.norm(m0, axis=-1, keepdims=True))
    clean = lievi.simulate_batch(
        jax.vmap(lievi.RigidBody)(inertias),
        lievi.DEP(),
        jnp.broadcast_to(jnp.eye(3), (n, 3, 3)),
        momenta,
        h=h,
        n_steps=n_steps,
        save=lievi.Save(every=every),
        system_axis=0,
    ).g
    observed = clean @ SO3.exp(jnp.asarray(sigma * rng.normal(size=clean.shape[:-1])))
    truth_loss = np.mean(np.sum((np.asarray(clean) - np.asarray(observed)) ** 2, (-2, -1)), -1)
    return inertias, momenta, observed, truth_loss


def default_start(out):
    inertias, momenta, observed, truth_loss = default_start_problem()
    t = time.perf_counter()
    fit = lievi.fit_inertia(observed, h=0.05, sample_every=5)
    jax.block_until_ready(fit.loss)
    seconds = time.perf_counter() - t
    normalised = lambda x: np.asarray(x) / np.asarray(x).sum(-1, keepdims=True)
    err = np.abs(normalised(fit.inertia) / normalised(inertias) - 1).max(-1)
    converged = np.asarray(fit.converged)
    excited = np.max(np.abs(np.asarray(momenta)), axis=-1) < 0.99
    ratio = np.asarray(fit.loss) / truth_loss
    record = dict(
        bodies=int(converged.size),
        seconds_total=seconds,
        converged=int(converged.sum()),
        reasons=np.bincount(np.asarray(fit.reason).ravel(), minlength=8).tolist(),
        iterations_quantiles={
            q: float(np.quantile(np.asarray(fit.iterations), q)) for q in (0.5, 0.9, 1)
        },
        error_quantiles_converged={q: float(np.quantile(err[converged], q)) for q in (0.5, 0.9, 1)},
        error_quantiles_converged_excited={
            q: float(np.quantile(err[converged & excited], q)) for q in (0.5, 0.9, 1)
        },
        fraction_excited_converged_within_2_percent=float(
            np.mean(err[converged & excited] <= 2e-2)
        ),
        loss_over_truth_loss_max=float(ratio.max()),
        worst=[
            dict(
                body=int(b),
                error=float(err[b]),
                loss=float(fit.loss[b]),
                truth_loss=float(truth_loss[b]),
                max_abs_m0_component=float(np.abs(np.asarray(momenta[b])).max()),
            )
            for b in np.argsort(err)[-3:][::-1]
        ],
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            load_average=os.getloadavg(),
            jax=jax.__version__,
            backend=jax.default_backend(),
        ),
    )
    print(json.dumps(record, indent=2))
    Path(out).parent.mkdir(parents=True, exist_ok=True)
    Path(out).write_text(json.dumps(record, indent=2) + "\n")


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--bodies", type=int, default=1000)
    parser.add_argument("--default-start", action="store_true")
    parser.add_argument("--out", default=None)
    args = parser.parse_args()
    results = Path(__file__).parent / "results"
    if args.default_start:
        default_start(args.out or str(results / "identification_default_start.json"))
        return
    args.out = args.out or str(results / "identification.json")

    inertias, momenta, observed, weights = problem(args.bodies)
    base = baseline(inertias, momenta, observed)

    # Time the parts of the fit: the optimiser's rounds (each with its compilation when a
    # new batch size first appears) and the rest (start, final report).
    rounds = []
    run = schedule.run

    def timed_run(problem, n_evals, carry, *rest):
        t = time.perf_counter()
        out = run(problem, n_evals, carry, *rest)
        jax.block_until_ready(out.it)
        rounds.append(
            dict(size=int(carry.it.shape[0]), seconds=time.perf_counter() - t, ticks=n_evals)
        )
        return out

    schedule.run = timed_run
    t = time.perf_counter()
    fit = lievi.fit_inertia(
        observed, h=H, sample_every=EVERY, inertia=GUESS, orientation_weight=weights
    )
    jax.block_until_ready(fit.loss)
    total = time.perf_counter() - t
    schedule.run = run

    normalised = lambda x: np.asarray(x) / np.asarray(x).sum(-1, keepdims=True)
    err = np.abs(normalised(fit.inertia) / normalised(inertias) - 1).max(-1)
    converged = np.asarray(fit.converged)
    excited = np.max(np.abs(np.asarray(momenta)), axis=-1) < 0.99
    iterations = np.asarray(fit.iterations)
    in_rounds = sum(r["seconds"] for r in rounds)
    sizes = sorted({r["size"] for r in rounds}, reverse=True)
    record = dict(
        bodies=args.bodies,
        steps_per_body=N_STEPS,
        samples=N_STEPS // EVERY + 1,
        seconds_total=total,
        seconds_in_rounds=in_rounds,
        seconds_start_and_report=total - in_rounds,
        rounds=len(rounds),
        batch_sizes=sizes,
        seconds_first_round_per_size={
            s: next(r["seconds"] for r in rounds if r["size"] == s) for s in sizes
        },
        baseline_forward_seconds=base["forward"],
        baseline_gradient_seconds=base["gradient"],
        fit_in_gradient_evaluations=total / base["gradient"],
        iterations_quantiles={q: float(np.quantile(iterations, q)) for q in (0.5, 0.9, 0.99, 1)},
        converged_fraction=float(converged.mean()),
        converged_fraction_excited=float(converged[excited].mean()),
        reasons=np.bincount(np.asarray(fit.reason).ravel(), minlength=8).tolist(),
        error_quantiles_converged_excited={
            q: float(np.quantile(err[excited & converged], q)) for q in (0.5, 0.9, 0.99, 1)
        },
        machine=dict(
            platform=platform.platform(),
            cpus=os.cpu_count(),
            load_average=os.getloadavg(),
            jax=jax.__version__,
            backend=jax.default_backend(),
        ),
    )
    print(json.dumps(record, indent=2))
    Path(args.out).parent.mkdir(parents=True, exist_ok=True)
    Path(args.out).write_text(json.dumps(record, indent=2) + "\n")


if __name__ == "__main__":
    main()
