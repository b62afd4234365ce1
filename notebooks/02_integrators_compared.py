# ---
# jupyter:
#   jupytext:
#     formats: ipynb,py:percent
#     text_representation:
#       extension: .py
#       format_name: percent
#       format_version: '1.3'
#       jupytext_version: 1.19.6
#   kernelspec:
#     display_name: Python 3 (ipykernel)
#     language: python
#     name: python3
# ---

# %% [markdown]
# # 02 — The integrators compared: work–precision, long-time energy, high order
#
# All of `lievi`'s integrators on the free rigid body, through the one entry point:
#
# | method | order | kind |
# |---|---|---|
# | `DEP(chart="exp")`, `DEP(chart="cayley")` | 2 | variational, implicit (paper §4) |
# | `MoserVeselov()` (DMV) | 2 | variational, implicit (paper §5) |
# | `LiePoissonSplitting()` | 2 | Lie–Poisson, explicit (paper §6) |
# | `RK4()` | 4 | classical, not geometric (baseline) |
# | `Composition(method, 4 or 6)` | 4, 6 | symmetric composition (triple jump, Kahan–Li) |
# | `PreprocessedMoserVeselov(order)` | 4, 6, 8, 10 | DMV with a modified step and an attitude correction (after Hairer–Vilmart 2006) |
#
# Test problems (docs/theory/test-problems.md): the Hairer–Vilmart body $I = (0.6, 0.8, 1.0)$ with
# $y_0 = (1.8, 0.4, -0.9)$, $Q_0 = I_3$, $T = 10$, and the HLW body $I = (2, 1, 2/3)$ for the
# long run. Errors are measured against DOP853 at rtol = atol = $10^{-13}$ (itself about
# $10^{-13}$ accurate). The full benchmark, with both Hairer–Vilmart bodies, the HLW body and
# wall times, is `benchmarks/accuracy.py`; its stored results are shown at the end.

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")
T = 2.0 if SMALL else 10.0  # final time of the work-precision study
STEPS = [50, 100] if SMALL else [25 * 2**k for k in range(8)]  # steps to T
N_LONG = 2_000 if SMALL else 100_000  # long run at h = 0.1 (HLW): T = 1e4
N_ACCEPT = 2_500  # order-6 preprocessed DMV at T = 10 (h = 0.004)

# %%
import time

import equinox as eqx
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)
import lievi
from lievi import diagnostics
from lievi._integrators._preprocessed_dmv import modified_moments_series

# %config InlineBackend.figure_formats = ["png"]
plt.rcParams.update({"figure.dpi": 100, "axes.grid": True, "grid.alpha": 0.3})
print("lievi", lievi.__version__, "| jax", jax.__version__, "| SMALL =", SMALL)

# %% [markdown]
# ## 1. Why DMV can be preprocessed to any order
#
# Plain DMV keeps not only the Casimir $C = |y|^2$ but also the energy
# $H = \tfrac12 y^\top I^{-1} y$ exactly:

# %%
body = lievi.RigidBody(jnp.array([0.6, 0.8, 1.0]))
y0 = jnp.array([1.8, 0.4, -0.9])
sol = lievi.simulate(body, lievi.MoserVeselov(), jnp.eye(3), y0, h=0.2, n_steps=500)
dH = float(diagnostics.relative_drift(diagnostics.energy(body, sol.g, sol.m)))
dC = float(diagnostics.relative_drift(diagnostics.casimirs(body, sol.m)))
print(f"DMV, h = 0.2, 500 steps: energy drift {dH:.1e}, Casimir drift {dC:.1e}")
assert dH < 1e-12 and dC < 1e-12

# %% [markdown]
# DMV is also symplectic on $T^*\mathrm{SO}(3)$ and commutes with rotations of the attitude.
# On each invariant torus of the integrable rigid body it is then a translation in the angle
# variables: **one DMV step of size $h$ is exactly the rigid-body flow over a modified time
# $\tau(h) = h + c_3 h^3 + c_5 h^5 + \dots$, followed by a rotation of the attitude about the
# body momentum by an angle $\rho(h)|y|$**, where $\tau$ and $\rho$ depend only on $h$, $H$, $C$.
# (Hairer and Vilmart say the same thing as "DMV is the exact solution of a rigid body with
# modified moments of inertia": DMV with moments $I/\alpha$ and step $h$ is DMV with moments
# $I$ and step $\alpha h$.)
#
# So `PreprocessedMoserVeselov(p)` runs DMV on a body with modified inverse moments
# $\alpha(h) I^{-1} + \beta(h)\,\mathrm{Id}$, where $\alpha$ and $\beta$ are series in $h^2$ whose
# coefficients depend only on $H$, $C$ and $I$ (Hairer–Vilmart's preprocessing), cut after
# $h^{p-2}$: order $p$, and with far smaller remainders than cutting the time series $\tau$.
# The series are computed in JAX, by truncated power series of the DMV step and of the exact
# flow (see `lievi/_integrators/_preprocessed_dmv.py`), once per trajectory (`prepare`); then
# each step is one DMV step. The coefficients for our body (even powers only — the method is
# symmetric):

# %%
alpha, beta = modified_moments_series(jnp.diag(1 / body.inertia), y0, 10)
np.set_printoptions(precision=4, suppress=False)
print("alpha(h) coefficients h^0..h^10:", np.asarray(alpha))
print("beta(h)  coefficients h^0..h^10:", np.asarray(beta))


# %% [markdown]
# ## 2. Work–precision on the Hairer–Vilmart body
#
# Error in $\Pi$ at $T$ against the number of steps, for every method (the preprocessing of
# `PreprocessedMoserVeselov` is part of the run). One compiled loop per method serves every
# step count. At N = 25 (h = 0.4) the Newton solves of the Moser–Veselov-based methods do not
# all converge on this body (`benchmarks/accuracy.py` reports those points as NaN; here they
# are plotted as they come).

# %%
@eqx.filter_jit
def final_state(system, integrator, g0, m0, h, n):
    if isinstance(integrator, lievi.PreprocessedMoserVeselov):
        integrator = integrator.prepare(system, m0, h)
    def step(_, state):
        g, m = state
        return integrator.step(system, g, m, h)[:2]
    return jax.lax.fori_loop(0, n, step, (g0, m0))

mv, split = lievi.MoserVeselov(), lievi.LiePoissonSplitting()
METHODS = {
    "DEP exp": lievi.DEP(), "DEP Cayley": lievi.DEP(chart="cayley"), "MV": mv,
    "splitting": split, "RK4": lievi.RK4(),
    "Comp4(MV)": lievi.Composition(mv, 4), "Comp6(MV)": lievi.Composition(mv, 6),
    "Comp4(splitting)": lievi.Composition(split, 4), "Comp6(splitting)": lievi.Composition(split, 6),
    "pDMV4": lievi.PreprocessedMoserVeselov(4), "pDMV6": lievi.PreprocessedMoserVeselov(6),
    "pDMV8": lievi.PreprocessedMoserVeselov(8), "pDMV10": lievi.PreprocessedMoserVeselov(10),
}
if SMALL:
    METHODS = {k: METHODS[k] for k in ("MV", "RK4", "Comp4(MV)", "pDMV6")}
g_ref, m_ref = lievi.reference_solution(body, jnp.eye(3), y0, [0.0, T])
errors, walls = {}, {}
for name, integrator in METHODS.items():
    errors[name], walls[name] = [], []
    for n in STEPS:
        h = jnp.asarray(T / n)
        jax.block_until_ready(final_state(body, integrator, jnp.eye(3), y0, h, jnp.asarray(n)))
        start = time.perf_counter()
        g, m = jax.block_until_ready(final_state(body, integrator, jnp.eye(3), y0, h, jnp.asarray(n)))
        walls[name].append(time.perf_counter() - start)
        errors[name].append(float(jnp.max(jnp.abs(m - m_ref[-1]))))

def fitted_order(errs):
    pts = [(n, e) for n, e in zip(STEPS, errs) if np.isfinite(e) and 1e-12 < e < 1e-2]
    if len(pts) < 2:
        return float("nan")
    return -np.polyfit(np.log([p[0] for p in pts]), np.log([p[1] for p in pts]), 1)[0]

print(f"{'method':17s} {'order':>6s}  error in Pi at T = {T:g} for N = {STEPS}")
for name, errs in errors.items():
    print(f"{name:17s} {fitted_order(errs):6.2f}  " + " ".join(f"{e:8.1e}" for e in errs))

# %%
fig, axes = plt.subplots(1, 2, figsize=(13, 5))
for name in errors:
    style = "--" if name.startswith("Comp") else (":" if name.startswith("pDMV") else "-")
    axes[0].loglog(STEPS, errors[name], style, marker="o", ms=3, label=name)
    axes[1].loglog(walls[name], errors[name], style, marker="o", ms=3, label=name)
axes[0].set(xlabel="steps to T", ylabel="max error in $\\Pi$ at T", title="error vs steps")
axes[1].set(xlabel="wall time [s] (jitted, compile apart; shared machine: indicative)",
            title="error vs wall time")
axes[0].legend(fontsize=8, ncol=2)
fig.suptitle(f"Hairer–Vilmart body I = (0.6, 0.8, 1.0), T = {T:g}")
fig.tight_layout()

# %% [markdown]
# ## 3. The accuracy bar: order-6 preprocessed DMV to $10^{-11}$ at $T = 10$

# %%
if not SMALL:
    g_ref10, m_ref10 = lievi.reference_solution(body, jnp.eye(3), y0, [0.0, 10.0])
    h = jnp.asarray(10.0 / N_ACCEPT)
    g, m = final_state(body, lievi.PreprocessedMoserVeselov(6), jnp.eye(3), y0, h, jnp.asarray(N_ACCEPT))
    err = float(jnp.max(jnp.abs(m - m_ref10[-1])))
    print(f"pDMV6, h = {float(h)}: error in Pi at T = 10 = {err:.1e}, "
          f"in Q = {float(jnp.max(jnp.abs(g - g_ref10[-1]))):.1e}")
    assert err <= 1e-11

# %% [markdown]
# ## 4. Long-time energy: geometric methods against RK4
#
# The HLW body at $h = 0.1$ to $T = 10^4$ ($10^5$ steps). The Lie–Poisson methods keep the
# Casimir to round-off; DMV and its preprocessed version keep the energy to round-off too;
# DEP and the splitting have a bounded $O(h^2)$ energy error; RK4 is more accurate per step
# but drifts, linearly in time, in both energy and Casimir.

# %%
hlw = lievi.RigidBody(jnp.array([2.0, 1.0, 2.0 / 3.0]))
m_hlw = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
LONG = {"DEP exp": lievi.DEP(), "splitting": split, "MV": mv, "RK4": lievi.RK4(),
        "pDMV6": lievi.PreprocessedMoserVeselov(6).prepare(hlw, m_hlw, 0.1)}
if SMALL:
    LONG = {k: LONG[k] for k in ("MV", "RK4", "pDMV6")}
fig, ax = plt.subplots(figsize=(10, 4.5))
for name, integrator in LONG.items():
    sol = lievi.simulate(hlw, integrator, jnp.eye(3), m_hlw, h=0.1, n_steps=N_LONG, save=lievi.Save(every=N_LONG // 1000))
    energy = np.asarray(diagnostics.energy(hlw, sol.g, sol.m))
    error = np.abs(energy - energy[0]) / energy[0]
    casimir = float(diagnostics.relative_drift(diagnostics.casimirs(hlw, sol.m)))
    print(f"{name:10s} max |dH/H| = {error.max():.1e}   Casimir drift = {casimir:.1e}")
    if name != "RK4":
        assert casimir < 1e-12
    ax.semilogy(np.asarray(sol.ts)[1:], np.maximum(error[1:], 1e-17), lw=0.8, label=name)
ax.set(xlabel="t", ylabel="|H - H_0| / H_0", title="HLW body, h = 0.1")
ax.legend(fontsize=8)
fig.tight_layout()

# %% [markdown]
# ## 5. The stored full benchmark (`benchmarks/accuracy.py`)
#
# Three bodies, every method, wall times, and the cost per step of the preprocessed DMV
# relative to plain DMV, measured in the same run. The figure is
# [`benchmarks/results/accuracy.png`](../benchmarks/results/accuracy.png).

# %%
import json
from pathlib import Path

results = Path("..") / "benchmarks" / "results"
if (results / "accuracy.json").exists():
    data = json.loads((results / "accuracy.json").read_text())
    for problem, rows in data["work_precision"]["problems"].items():
        print(problem + ": fitted orders " + ", ".join(f"{k} {v['fitted_order']:.2f}" for k, v in rows.items()))
    cost = data["cost"]
    print("cost per step / plain DMV: " + ", ".join(
        f"{k} {v['ratio_to_MV']:.2f}" for k, v in cost.items() if k.startswith("pDMV")))
    print("figure: benchmarks/results/accuracy.png")
else:
    print("run `python benchmarks/accuracy.py` to produce the stored results")
