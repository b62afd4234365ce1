"""Work–precision of the preprocessed DMV (orders 4–10) against compositions and DEP.

On the two free rigid bodies of Hairer & Vilmart (J. Phys. A 39 (2006) 13225):
`I = (0.6, 0.8, 1.0)` and the flat "water molecule" `I = (0.345, 0.653, 1.0)`,
`y₀ = (1.8, 0.4, −0.9)`, `Q₀ = Id`, integrate to T = 10 with N = 25·2^k steps and measure
the maximum error in Π over the run against DOP853 (rtol = atol = 1e-14 requested, scipy
uses 2.2e-14; the reference is ~1e-14 accurate) and the wall time of the jitted run
(compile apart, best of 3; the preprocessing of the preprocessed DMV included); the
figure's cost axis is N × the seconds per step of the longest run. Methods:
`PreprocessedMoserVeselov(4, 6, 8, 10)`, plain `MoserVeselov`, `Composition(MoserVeselov,
4 / 6)`, `DEP` (exp chart) and `Composition(DEP, 4)`. Alongside, the errors of
Hairer–Vilmart's own preprocessed DMV code on the same problem (`HAIRER_VILMART`, see
`docs/preprocessed_dmv.md`). Also: the relative energy error over T = 1e4 (h = 0.1,
Hairer–Lubich–Wanner body `I = (2, 1, 2/3)`, `Π₀ = (cos 1.1, 0, sin 1.1)`) of the geometric
methods against RK4, and the cost per step of the prepared preprocessed DMV relative to
plain DMV (same run, same machine, 1e4 steps). Writes `benchmarks/results/accuracy.json`
and `accuracy.png`, prints tables. The machine may be shared: wall times are indicative,
ratios within one run are the figure to quote.

    python benchmarks/accuracy.py            # full (~5–10 min on 2 cores)
    python benchmarks/accuracy.py --quick    # smoke test (a few methods, small sizes)
    python benchmarks/accuracy.py --cost-only  # re-measure the cost per step only
    python benchmarks/accuracy.py --drift    # 10⁶ steps: error against time (~10 min)
    taskset -c 0 python benchmarks/accuracy.py --batch-cost   # batched cost (~2 min)

`--batch-cost` times `PreprocessedMoserVeselov(8)` in `simulate_batch` per body-step, on
its batch kernel and on the generic path (a subclass: each body's `init` and step under
`jax.vmap`), beside `MoserVeselov()` and `RKMK8()`, and its start-up (the modified moments,
µs per body: the kernel's, fitted for the shared body, and each body's own series, the
path of a batch of bodies): HLW body, `Π₀` scaled per body, h = 0.1, 1000 steps, one saved state, under
`jax.jit`, CPU time, best of 5 with the methods alternated in one process, batches 256,
1024 and 4096. Writes `results/accuracy_batch_cost.json`.

`--drift` is the long-run picture: 10⁶ steps of h = 0.1 (T = 10⁵) of one body, the
Hairer–Lubich–Wanner free body and the benchmark's heavy top (`work_precision.py`'s), with
structure-preserving methods (splitting, `DEP`, the order-8 composition of the splitting,
the preprocessed Moser–Veselov of order 8) beside methods that are not (`RKMK8`, diffrax's
`Dopri8` and `Tsit5` at the same step). It plots against time the energy error (bounded
for the variational methods, growing for the others), the momentum-map error, and, on the
integrable HLW body, the attitude error against an independent diffrax `Dopri8` run at
rtol = atol = 1e-13 (phase error linear in t for the symplectic methods, quadratic for the
others). The heavy top is chaotic: only its invariants are compared. Writes
`results/accuracy_drift.json` and `.png`.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import time
import warnings

import jax

jax.config.update("jax_enable_x64", True)
import equinox as eqx  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402
from lievi import diagnostics as dg  # noqa: E402
from lievi._integrators._preprocessed_dmv import (  # noqa: E402
    modified_principal_moments,
    shared_modified_principal_moments,
)

RESULTS_DIR = pathlib.Path(__file__).parent / "results"

PROBLEMS = {
    "HLW": (jnp.array([2.0, 1.0, 2.0 / 3.0]), jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])),
    "HV": (jnp.array([0.6, 0.8, 1.0]), jnp.array([1.8, 0.4, -0.9])),
    "HV water": (jnp.array([0.345, 0.653, 1.0]), jnp.array([1.8, 0.4, -0.9])),
}
WORK_PRECISION_PROBLEMS = ("HV", "HV water")

# max |Π error| over T = 10 of Hairer–Vilmart's preprocessed DMV (their coefficient formulas
# and quaternion DMV step, re-run in float64 against the same DOP853 reference), N = 100 …
# 3200; entries ≲ 3e-14 are round-off. See docs/preprocessed_dmv.md.
HAIRER_VILMART = {
    "HV": {
        4: [1.86e-3, 1.13e-4, 6.99e-6, 4.36e-7, 2.72e-8, 1.70e-9],
        6: [5.75e-6, 8.73e-8, 1.35e-9, 2.11e-11, 3.34e-13, 9.55e-15],
        8: [9.47e-9, 3.60e-11, 1.49e-13, 1.67e-15, 9.88e-15, 1.19e-14],
        10: [9.83e-12, 8.72e-15, 6.66e-15, 4.66e-15, 9.88e-15, 1.19e-14],
    },
    "HV water": {
        4: [4.50e-2, 2.58e-3, 1.58e-4, 9.80e-6, 6.12e-7, 3.82e-8],
        6: [3.21e-4, 4.55e-6, 6.95e-8, 1.08e-9, 1.69e-11, 2.03e-13],
        8: [1.55e-6, 5.55e-9, 2.13e-11, 7.33e-14, 3.70e-14, 1.93e-14],
        10: [3.91e-9, 3.45e-12, 9.49e-15, 3.59e-14, 3.70e-14, 1.93e-14],
    },
}
HAIRER_VILMART_STEPS = [100, 200, 400, 800, 1600, 3200]


def methods(quick: bool):
    mv, split = lievi.MoserVeselov(), lievi.LiePoissonSplitting()
    full = {
        "DEP exp": lievi.DEP(chart="exp"),
        "DEP Cayley": lievi.DEP(chart="cayley"),
        "MV": mv,
        "splitting": split,
        "RK4": lievi.RK4(),
        "Comp4(DEP exp)": lievi.Composition(lievi.DEP(), 4),
        "Comp4(MV)": lievi.Composition(mv, 4),
        "Comp6(MV)": lievi.Composition(mv, 6),
        "pDMV4": lievi.PreprocessedMoserVeselov(4),
        "pDMV6": lievi.PreprocessedMoserVeselov(6),
        "pDMV8": lievi.PreprocessedMoserVeselov(8),
        "pDMV10": lievi.PreprocessedMoserVeselov(10),
    }
    if quick:
        keep = ("DEP exp", "MV", "Comp4(MV)", "pDMV6")
        return {k: full[k] for k in keep}
    return full


WORK_PRECISION_METHODS = (
    "DEP exp",
    "Comp4(DEP exp)",
    "MV",
    "Comp4(MV)",
    "Comp6(MV)",
    "pDMV4",
    "pDMV6",
    "pDMV8",
    "pDMV10",
)


@eqx.filter_jit
def max_error_run(system, integrator, g0, m0, h, n, m_ref):
    """`n` steps (traced: one compile for every n), preprocessing included; returns
    `max_k |Π_k − m_ref[k]|` (`m_ref` padded to a fixed length) and whether every step
    succeeded."""
    if isinstance(integrator, lievi.PreprocessedMoserVeselov):
        integrator = integrator.prepare(system, m0, h)

    def body(k, state):
        g, m, worst, ok = state
        g, m, info = integrator.step(system, g, m, h)
        worst = jnp.maximum(worst, jnp.max(jnp.abs(m - m_ref[k + 1])))
        return g, m, worst, ok & (info.result == lievi.RESULTS.successful)

    state = (g0, m0, jnp.zeros((), m0.dtype), jnp.array(True))
    return jax.lax.fori_loop(0, n, body, state)[2:]


def timed(fn, *args, repeats=3):
    jax.block_until_ready(fn(*args))  # compile (or cache hit)
    best, out = np.inf, None
    for _ in range(repeats):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return best, out


def work_precision(quick: bool):
    T = 2.0 if quick else 10.0
    steps = [25, 50] if quick else [25 * 2**k for k in range(8)]
    problems = ("HV",) if quick else WORK_PRECISION_PROBLEMS
    chosen = {k: v for k, v in methods(quick).items() if k in WORK_PRECISION_METHODS}
    out = {"T": T, "steps": steps, "error": "max |Π error| over the run", "problems": {}}
    padded = max(steps) + 1
    for pname in problems:
        inertia, m0 = PROBLEMS[pname]
        body = lievi.RigidBody(inertia)
        g0 = jnp.eye(3)
        references = {}
        for n in steps:
            with warnings.catch_warnings():  # scipy raises rtol to 100 ulps itself
                warnings.simplefilter("ignore", UserWarning)
                _, m_ref = lievi.reference_solution(
                    body, g0, m0, np.linspace(0.0, T, n + 1), rtol=1e-14, atol=1e-14
                )
            references[n] = jnp.asarray(np.pad(m_ref, ((0, padded - n - 1), (0, 0))))
        rows = {}
        for name, integrator in chosen.items():
            err_m, wall = [], []
            for n in steps:
                h = jnp.asarray(T / n)
                args = (body, integrator, g0, m0, h, jnp.asarray(n), references[n])
                seconds, (error, ok) = timed(max_error_run, *args)
                err_m.append(float(error) if bool(ok) and np.isfinite(error) else float("nan"))
                wall.append(seconds)
            finite = [(n, e) for n, e in zip(steps, err_m) if np.isfinite(e) and 1e-12 < e < 1e-1]
            slope = (
                float(
                    -np.polyfit(np.log([n for n, _ in finite]), np.log([e for _, e in finite]), 1)[
                        0
                    ]
                )
                if len(finite) >= 2
                else float("nan")
            )
            # Cost model for the figure: N × seconds per step of the longest run (short
            # runs are dominated by dispatch and, on a shared machine, by noise).
            per_step = wall[-1] / steps[-1]
            rows[name] = {
                "error_m": err_m,
                "wall_s": wall,
                "s_per_step": per_step,
                "cost_s": [n * per_step for n in steps],
                "fitted_order": slope,
            }
            print(
                f"{pname:9s} {name:15s} order≈{slope:5.2f}  " + " ".join(f"{e:8.1e}" for e in err_m)
            )
        if pname in HAIRER_VILMART and not quick:
            for order, reference in HAIRER_VILMART[pname].items():
                ours = [
                    rows[f"pDMV{order}"]["error_m"][steps.index(n)] for n in HAIRER_VILMART_STEPS
                ]
                ratio = [a / b if b > 3e-14 else float("nan") for a, b in zip(ours, reference)]
                rows[f"pDMV{order}"]["hairer_vilmart_error_m"] = reference
                rows[f"pDMV{order}"]["ratio_to_hairer_vilmart"] = ratio
                print(
                    f"{pname:9s} pDMV{order:<2d} / Hairer–Vilmart, N = 100…3200: "
                    + " ".join(f"{r:5.2f}" for r in ratio)
                )
        out["problems"][pname] = rows
    return out


def long_time_energy(quick: bool):
    inertia, m0 = PROBLEMS["HLW"]
    body = lievi.RigidBody(inertia)
    h = 0.1
    n_steps, save_every = (2_000, 20) if quick else (100_000, 100)
    chosen = (
        ("MV", "RK4", "pDMV6")
        if quick
        else ("DEP exp", "MV", "splitting", "RK4", "Comp4(MV)", "pDMV6")
    )
    all_methods = methods(False)
    out = {"h": h, "T": h * n_steps, "methods": {}}
    for name in chosen:
        integrator = all_methods[name]
        if isinstance(integrator, lievi.PreprocessedMoserVeselov):
            integrator = integrator.prepare(body, m0, h)
        sol = lievi.simulate(
            body,
            integrator,
            jnp.eye(3),
            m0,
            h=h,
            n_steps=n_steps,
            save=lievi.Save(every=save_every),
        )
        energy = dg.energy(body, sol.g, sol.m)
        error = np.abs(np.asarray((energy - energy[0]) / energy[0]))
        casimir = float(dg.relative_drift(dg.casimirs(body, sol.m)))
        out["methods"][name] = {
            "t": np.asarray(sol.ts).tolist(),
            "energy_error": error.tolist(),
            "max_energy_error": float(error.max()),
            "casimir_drift": casimir,
        }
        print(
            f"T = {h * n_steps:g}: {name:10s} max |ΔH/H| = {error.max():.1e}, Casimir drift {casimir:.1e}"
        )
    return out


def cost_ratio(quick: bool):
    """Seconds per step of the (prepared) preprocessed DMV over plain DMV, same run."""
    inertia, m0 = PROBLEMS["HV"]
    body = lievi.RigidBody(inertia)
    n = 1_000 if quick else 4_000
    h = jnp.asarray(0.01)
    out = {"n_steps": n}
    # The body is an argument, not a closed-over constant: as under `simulate`, it is traced.
    run = eqx.filter_jit(
        lambda integrator, body, m0: jax.lax.fori_loop(
            0, n, lambda _, s: integrator.step(body, s[0], s[1], h)[:2], (jnp.eye(3), m0)
        )
    )
    prepare = eqx.filter_jit(lambda integrator, body, m0: integrator.prepare(body, m0, h))
    candidates = {"MV": lievi.MoserVeselov()}
    for order in (4, 6, 8, 10):
        candidates[f"pDMV{order}"] = lievi.PreprocessedMoserVeselov(order).prepare(body, m0, h)
    for integrator in candidates.values():
        jax.block_until_ready(run(integrator, body, m0))  # compile
    # Round robin (order reversed every other round), the ratio to the MV run of the same
    # round, median over rounds: load on a shared machine changes slowly compared with
    # one run and hits neighbouring runs alike; the median drops the rounds it does not.
    seconds = {name: [] for name in candidates}
    names = list(candidates)
    for k in range(5 if quick else 25):
        for name in names if k % 2 == 0 else names[::-1]:
            start = time.perf_counter()
            jax.block_until_ready(run(candidates[name], body, m0))
            seconds[name].append(time.perf_counter() - start)
    mv = np.asarray(seconds["MV"])
    mv_s = float(np.median(mv))
    for order in (4, 6, 8, 10):
        mine = np.asarray(seconds[f"pDMV{order}"])
        ratio = float(np.median(mine / mv))
        prep_s, _ = timed(prepare, lievi.PreprocessedMoserVeselov(order), body, m0)
        out[f"pDMV{order}"] = {
            "s_per_step": float(np.median(mine)) / n,
            "ratio_to_MV": ratio,
            "ratio_to_MV_best": float(mine.min() / mv.min()),
            "prepare_s": prep_s,
        }
        print(
            f"pDMV{order}: {ratio:.2f}× plain DMV per step (median of {len(mv)} paired "
            f"rounds; best/best {mine.min() / mv.min():.2f}×); preprocessing "
            f"{prep_s * 1e3:.2f} ms once"
        )
    out["MV_s_per_step"] = mv_s / n
    print(f"plain DMV: {mv_s / n * 1e6:.2f} µs per step")
    return out


# ---- the long-run drift picture (`--drift`) -----------------------------------------------

DRIFT_PROBLEMS = {
    # name: (moments, Π₀, tilt of g₀ (rotation vector), gravity)
    "HLW body": ((2.0, 1.0, 2.0 / 3.0), (np.cos(1.1), 0.0, np.sin(1.1)), (0, 0, 0), False),
    "heavy top": ((0.6, 0.8, 1.0), (0.5, 0.3, 1.2), (0.3, -0.2, 0.1), True),
}
# The heavy top's constants (mass, centre of mass, gravity), as in work_precision.py.
TOP = (1.0, (0.0, 0.0, 0.5), 1.0)


def drift_methods(gravity: bool):
    split = lievi.LiePoissonSplitting()
    chosen = {
        "splitting": split,
        "DEP exp": lievi.DEP(),
        "splitting ∘ 8": lievi.Composition(split, order=8),
        "RKMK8": lievi.RKMK8(),
    }
    if not gravity:
        chosen["pDMV8"] = lievi.PreprocessedMoserVeselov(8)
    return chosen


def drift_system(moments, gravity):
    if gravity:
        mass, rho, gee = TOP
        return lievi.heavy_top(
            jnp.asarray(moments), mass, jnp.asarray(rho), gee, inertia_about="center_of_mass"
        )
    return lievi.RigidBody(jnp.asarray(moments))


def diffrax_drift(system, gravity, g0, m0, t1, n_saves, solver, h=None, tol=None):
    """One body, state `(Π, g)`: `Π̇ = Π × Ω (+ m γ Γ × ρ)`, `ġ = g Ω̂`, saved at `n_saves + 1`
    evenly spaced times; constant step `h`, or PID at rtol = atol = `tol`. The inertia is the
    system's (about the fixed point, for the top)."""
    import diffrax

    inverse = 1.0 / jnp.asarray(system.inertia)
    mass, rho, gee = TOP
    torque = mass * gee * jnp.asarray(rho)

    def field(t, y, args):
        Pi, g = y
        omega = Pi * inverse
        dPi = jnp.cross(Pi, omega) + (jnp.cross(g[2], torque) if gravity else 0.0)
        return dPi, g @ lievi.SO3.hat(omega)

    ts = jnp.linspace(0.0, t1, n_saves + 1)
    if tol is None:
        control = dict(dt0=h, stepsize_controller=diffrax.ConstantStepSize())
        max_steps = int(round(t1 / h)) + 1
    else:
        control = dict(dt0=None, stepsize_controller=diffrax.PIDController(rtol=tol, atol=tol))
        max_steps = int(t1 * 200)

    @jax.jit
    def run(y0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field), getattr(diffrax, solver)(), t0=0.0, t1=t1, y0=y0,
            saveat=diffrax.SaveAt(ts=ts), max_steps=max_steps, adjoint=diffrax.ForwardMode(),
            throw=False, **control,
        )  # fmt: skip
        return sol.ys, sol.result == diffrax.RESULTS.successful

    seconds, ((m, g), ok) = timed(run, (m0, g0), repeats=1)
    return g, m, seconds, bool(ok)


def three_digits(values):
    """A list of errors to three significant digits (the JSON stays small)."""
    return [float(f"{v:.3g}") for v in np.asarray(values)]


def drift(n_steps: int, h: float = 0.1, n_saves: int = 1000):
    t1 = n_steps * h
    out = {"h": h, "n_steps": n_steps, "T": t1, "problems": {}}
    for pname, (moments, m0, tilt, gravity) in DRIFT_PROBLEMS.items():
        system = drift_system(moments, gravity)
        g0 = lievi.SO3.exp(jnp.asarray(tilt, dtype=float))
        m0 = jnp.asarray(m0)
        runs = {}
        for name, integrator in drift_methods(gravity).items():
            start = time.perf_counter()
            sol = lievi.simulate(
                system, integrator, g0, m0, h=h, n_steps=n_steps,
                save=lievi.Save(every=n_steps // n_saves), throw=False,
            )  # fmt: skip
            ok = bool(sol.result == lievi.RESULTS.successful)
            runs[name] = (sol.g, sol.m, time.perf_counter() - start, ok)  # with compilation
        for solver in ("Dopri8", "Tsit5"):
            runs[f"diffrax {solver}"] = diffrax_drift(
                system, gravity, g0, m0, t1, n_saves, solver, h=h
            )
        ts = np.linspace(0.0, t1, n_saves + 1)
        reference = None
        if not gravity:  # integrable: the attitude is a fair target
            g_ref, _, ref_s, ref_ok = diffrax_drift(
                system, gravity, g0, m0, t1, n_saves, "Dopri8", tol=1e-13
            )
            reference = np.asarray(g_ref) if ref_ok else None
            print(f"{pname}: reference (diffrax Dopri8, tol 1e-13) {ref_s:.0f} s, ok {ref_ok}")
        H0 = float(dg.energy(system, m=m0, g=g0))
        J0 = np.asarray(dg.spatial_momentum(system, g0, m0))
        rows = {}
        for name, (g, m, seconds, ok) in runs.items():
            g, m = np.asarray(g), np.asarray(m)
            H = np.asarray(dg.energy(system, m=jnp.asarray(m), g=jnp.asarray(g)))
            J = np.asarray(dg.spatial_momentum(system, jnp.asarray(g), jnp.asarray(m)))
            dJ = (J - J0)[:, 2:] if gravity else J - J0  # the tops keep only the vertical part
            row = {
                "seconds": seconds,
                "ok": ok,
                "energy_error": three_digits(np.abs(H - H0) / abs(H0)),
                "momentum_error": three_digits(
                    np.linalg.norm(dJ, axis=-1) / float(jnp.linalg.norm(m0))
                ),
            }
            if reference is not None:
                chord = np.linalg.norm(g - reference, axis=(-2, -1)) / (2 * np.sqrt(2))
                row["attitude_error"] = three_digits(2 * np.arcsin(np.clip(chord, 0.0, 1.0)))
            rows[name] = row
            half = len(ts) // 2
            energy = np.asarray(row["energy_error"])
            print(
                f"{pname:9s} {name:16s} {seconds:7.1f} s (with compiling)  max |ΔH/H| {energy.max():.1e} "
                f"(2nd half mean / 1st half mean {energy[half:].mean() / max(energy[1:half].mean(), 1e-300):.2f}), "
                f"momentum {max(row['momentum_error']):.1e}"
                + (
                    f", attitude at T {row['attitude_error'][-1]:.1e}"
                    if reference is not None
                    else ""
                )
            )
        out["problems"][pname] = {"t": ts.tolist(), "methods": rows}
    return out


def plot_drift(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problems = results["problems"]
    fig, axes = plt.subplots(len(problems), 3, figsize=(16, 4.4 * len(problems)))
    axes = np.atleast_2d(axes)
    quantities = ("energy_error", "momentum_error", "attitude_error")
    labels = ("|ΔH / H₀|", "momentum-map error / |Π₀|", "attitude error [rad]")
    names = list(dict.fromkeys(n for p in problems.values() for n in p["methods"]))
    colour = {name: f"C{k}" for k, name in enumerate(names)}  # one colour a method
    for row, (pname, p) in enumerate(problems.items()):
        t = np.asarray(p["t"][1:])
        for col, (quantity, label) in enumerate(zip(quantities, labels)):
            ax = axes[row, col]
            drawn = [(name, r[quantity]) for name, r in p["methods"].items() if quantity in r]
            if not drawn:  # the chaotic top: no attitude target
                ax.text(0.5, 0.5, "chaotic: no trajectory target", ha="center", va="center")
                ax.set_axis_off()
                continue
            for name, values in drawn:
                style = "--" if name.startswith(("RKMK", "diffrax")) else "-"
                ax.loglog(
                    t, np.maximum(values[1:], 1e-17), style, color=colour[name], lw=0.9, label=name
                )
            ax.set(xlabel="t", ylabel=label, title=f"{pname}: {label}")
            ax.grid(True, which="both", alpha=0.3)
        axes[row, 0].legend(fontsize=7)
    fig.suptitle(
        f"{results['n_steps']:,} steps of h = {results['h']} (T = {results['T']:g}); solid: "
        "structure-preserving, dashed: not"
    )
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    problems = results["work_precision"]["problems"]
    steps = results["work_precision"]["steps"]
    fig, axes = plt.subplots(len(problems) + 1, 2, figsize=(12, 4.2 * (len(problems) + 1)))
    axes = np.atleast_2d(axes)
    for row, (pname, rows) in enumerate(problems.items()):
        for name, r in rows.items():
            style = "--" if name.startswith("Comp") else ("-" if name.startswith("pDMV") else ":")
            (line,) = axes[row, 0].loglog(steps, r["error_m"], style, marker="o", ms=3, label=name)
            axes[row, 1].loglog(r["cost_s"], r["error_m"], style, marker="o", ms=3, label=name)
            if "hairer_vilmart_error_m" in r:
                axes[row, 0].loglog(
                    HAIRER_VILMART_STEPS,
                    r["hairer_vilmart_error_m"],
                    "x",
                    color=line.get_color(),
                    ms=7,
                )
        axes[row, 0].set(
            xlabel="steps to T = 10",
            ylabel="max |Π error| over the run",
            title=f"{pname}: error vs steps (×: Hairer–Vilmart's code)",
        )
        axes[row, 1].set(
            xlabel="cost [s]: N × seconds per step (jitted, one body, CPU)",
            title=f"{pname}: error vs cost",
        )
        for ax in axes[row]:
            ax.grid(True, which="both", alpha=0.3)
    axes[0, 1].legend(fontsize=7, ncol=2)
    energy = results["long_time_energy"]
    for name, r in energy["methods"].items():
        axes[-1, 0].semilogy(
            r["t"][1:], np.maximum(r["energy_error"][1:], 1e-17), label=name, lw=0.8
        )
    axes[-1, 0].set(
        xlabel="t",
        ylabel="|ΔH/H|",
        title=f"HLW, h = {energy['h']}: energy error to T = {energy['T']:g}",
    )
    axes[-1, 0].legend(fontsize=7)
    cost = results["cost"]
    orders = [k for k in cost if k.startswith("pDMV")]
    axes[-1, 1].bar(["MV"] + orders, [1.0] + [cost[k]["ratio_to_MV"] for k in orders])
    axes[-1, 1].axhline(1.1, color="k", ls="--", lw=0.8)
    axes[-1, 1].set(ylabel="cost per step / plain DMV", title="preprocessed DMV: cost per step")
    fig.tight_layout()
    fig.savefig(path, dpi=110)


class _GenericPreprocessed(lievi.PreprocessedMoserVeselov):
    """The generic path (a subclass has no kernel): each body's `init` and step under
    `jax.vmap`, the cost before the kernel."""


def batch_cost(batches=(256, 1024, 4096), steps=1000, repeats=5) -> dict:
    """`--batch-cost`: ns per body-step of `PreprocessedMoserVeselov(8)` on its kernel and
    on the generic path beside `MoserVeselov` and `RKMK8`, and µs per body of its
    start-up (the modified moments alone, batched: fitted for the shared body, as the
    kernel does, and each body's series), HLW body (module docstring)."""
    inertia, m0, h = jnp.array([2.0, 1.0, 2 / 3]), jnp.array([np.cos(1.1), 0.0, np.sin(1.1)]), 0.1
    body = lievi.RigidBody(inertia)
    methods = {
        "PMV(8) kernel": lievi.PreprocessedMoserVeselov(8),
        "PMV(8) generic": _GenericPreprocessed(8),
        "MoserVeselov": lievi.MoserVeselov(),
        "RKMK8": lievi.RKMK8(),
    }
    save = lievi.Save(every=steps, stats=False)
    out = {"problem": "HLW body", "h": h, "steps": steps, "rows": []}
    for batch in batches:
        m0s = m0 * (1 + 0.2 * jnp.sin(jnp.arange(batch)))[:, None]
        g0s = jnp.broadcast_to(jnp.eye(3), (batch, 3, 3))
        calls = {
            name: jax.jit(
                lambda m, method=method, g0s=g0s: (
                    lievi.simulate_batch(
                        body, method, g0s, m, h=h, n_steps=steps, save=save, throw=False
                    ).m
                )
            )
            for name, method in methods.items()
        }
        calls["start-up"] = jax.jit(lambda m: shared_modified_principal_moments(inertia, m, h, 8))
        calls["per-body start-up"] = jax.jit(
            jax.vmap(lambda m: modified_principal_moments(inertia, m, h, 8))
        )
        best = dict.fromkeys(calls, np.inf)
        for f in calls.values():
            jax.block_until_ready(f(m0s))
        for _ in range(repeats):  # the methods alternated
            for name, f in calls.items():
                t = time.process_time()
                jax.block_until_ready(f(m0s))
                best[name] = min(best[name], time.process_time() - t)
        row = {"batch": batch}
        for name in methods:
            row[f"{name} ns per body-step"] = best[name] / (batch * steps) * 1e9
        row["PMV(8) start-up us per body"] = best["start-up"] / batch * 1e6
        row["PMV(8) per-body start-up us per body"] = best["per-body start-up"] / batch * 1e6
        out["rows"].append(row)
        print(
            "  ".join(
                f"{k} {v:.4g}" if isinstance(v, float) else f"{k} {v}" for k, v in row.items()
            )
        )
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="smoke test: few methods, small sizes")
    parser.add_argument("--out", default=None, help="output directory (default benchmarks/results)")
    parser.add_argument(
        "--cost-only",
        action="store_true",
        help="re-measure only the cost per step; keep the other stored results",
    )
    parser.add_argument(
        "--drift",
        type=int,
        nargs="?",
        const=1_000_000,
        default=None,
        help="only the long-run drift picture, with this many steps (default 10⁶)",
    )
    parser.add_argument(
        "--batch-cost",
        action="store_true",
        help="only the batched per body-step cost of PreprocessedMoserVeselov(8) and its start-up",
    )
    args = parser.parse_args()
    out_dir = pathlib.Path(args.out) if args.out else RESULTS_DIR
    out_dir.mkdir(parents=True, exist_ok=True)
    suffix = "_quick" if args.quick else ""
    start = time.perf_counter()
    if args.batch_cost:
        results = {"device": str(jax.devices()[0]), "dtype": "float64", **batch_cost()}
        results["load_average"] = os.getloadavg()
        (out_dir / "accuracy_batch_cost.json").write_text(json.dumps(results, indent=1))
        print(f"wrote {out_dir / 'accuracy_batch_cost.json'}")
        return
    if args.drift:
        results = {"device": str(jax.devices()[0]), "dtype": "float64", **drift(args.drift)}
        results["total_s"] = time.perf_counter() - start
        (out_dir / "accuracy_drift.json").write_text(json.dumps(results, indent=1))
        plot_drift(results, out_dir / "accuracy_drift.png")
        print(f"wrote {out_dir / 'accuracy_drift.json'} and .png in {results['total_s']:.0f}s")
        return
    if args.cost_only:
        results = json.loads((out_dir / f"accuracy{suffix}.json").read_text())
        results["cost"] = cost_ratio(args.quick)
    else:
        results = {
            "device": str(jax.devices()[0]),
            "dtype": "float64",
            "work_precision": work_precision(args.quick),
            "long_time_energy": long_time_energy(args.quick),
            "cost": cost_ratio(args.quick),
        }
    results["total_s"] = time.perf_counter() - start
    (out_dir / f"accuracy{suffix}.json").write_text(json.dumps(results, indent=1))
    plot(results, out_dir / f"accuracy{suffix}.png")
    print(f"wrote {out_dir / f'accuracy{suffix}.json'} and .png in {results['total_s']:.0f}s")


if __name__ == "__main__":
    main()
