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
# # 04 — Batched rollouts: 10⁵ rigid bodies at once
#
# `lievi.simulate_batch` integrates many bodies in one compiled loop: each body may have its
# own inertia, initial state and step size. For the rigid body with principal moments and
# `DEP` (both charts), `MoserVeselov`, `LiePoissonSplitting` or `RK4` it uses a
# structure-of-arrays fast path (closed-form Newton or explicit updates on component arrays,
# `lievi/_kernels/_so3.py`, `lievi/_kernels/_explicit.py`) whose iterates equal per-body
# `lievi.simulate` to round-off (`tests/test_batch.py`).
#
# This notebook
#
# 1. integrates $10^5$ random bodies and shows the distribution, over the batch, of the
#    Casimir error (round-off for every body) and of the energy error (bounded, of size
#    $O(h^2)$), in float64 and float32;
# 2. shows the intermediate-axis (Dzhanibekov) flip across a batch of bodies started near
#    the unstable axis, and checks the time to the first flip against the linearised growth
#    rate;
# 3. shows that a failing body is reported per body and does not stop the others.

# %% [markdown]
# **Sizes.** With `LIEVI_NOTEBOOK_SMALL=1` (as the test suite does) the notebook runs at a
# small size; the stored outputs are from a full-size run.

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")

N_BODIES = 2_000 if SMALL else 100_000  # random bodies
H = 0.05  # step size
N_STEPS = 400 if SMALL else 2_000  # T = 20 (small) or 100
N_SAVES = 40  # saved states per body (memory: N_BODIES × N_SAVES × 3 numbers)
N_FLIP = 64 if SMALL else 1_000  # bodies in the Dzhanibekov batch

# %%
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)
import lievi
from lievi import diagnostics as dg

print(jax.devices()[0], "| fast path:", lievi.advanced.has_fast_path(lievi.RigidBody(jnp.ones(3)), lievi.DEP()))

# %% [markdown]
# ## 1. Conservation across a batch of random bodies
#
# Principal moments uniform in $[0.5, 2]$, unit momenta in random directions, $g_0 = I_3$.
# Each body's inertia is a leaf of a batched `RigidBody` (`jax.vmap(lievi.RigidBody)`),
# passed with `system_axis=0`. Only the momenta are stored (`save=lievi.Save(g=False, stats=False)`), every
# `N_STEPS // N_SAVES` steps.

# %%
rng = np.random.default_rng(0)
inertia = rng.uniform(0.5, 2.0, size=(N_BODIES, 3))
m0 = rng.normal(size=(N_BODIES, 3))
m0 /= np.linalg.norm(m0, axis=1, keepdims=True)
g0 = np.broadcast_to(np.eye(3), (N_BODIES, 3, 3))

INTEGRATORS = {"DEP exp": lievi.DEP(chart="exp"), "DEP Cayley": lievi.DEP(chart="cayley"),
               "Moser–Veselov": lievi.MoserVeselov(), "splitting": lievi.LiePoissonSplitting()}


def run(integrator, dtype):
    bodies = jax.vmap(lievi.RigidBody)(jnp.asarray(inertia, dtype))
    args = (bodies, integrator, jnp.asarray(g0, dtype), jnp.asarray(m0, dtype))
    kwargs = dict(h=jnp.asarray(H, dtype), n_steps=N_STEPS, save=lievi.Save(every=N_STEPS // N_SAVES, g=False, stats=False),
                   system_axis=0, throw=False)
    compiled = jax.jit(lambda b, g, m: lievi.simulate_batch(b, integrator, g, m, **kwargs)).lower(
        bodies, *args[2:]).compile()  # timed apart from the run below
    start = time.perf_counter()
    sol = jax.block_until_ready(compiled(bodies, *args[2:]))
    elapsed = time.perf_counter() - start
    assert np.all(np.asarray(sol.result) == lievi.RESULTS.successful)
    m = np.asarray(sol.m, np.float64)
    body64 = jax.vmap(lievi.RigidBody)(jnp.asarray(inertia))
    energy = np.asarray(jax.vmap(dg.energy)(body64, jnp.asarray(m)))
    casimir = np.sum(m**2, axis=-1)
    return {
        "rate": N_BODIES * N_STEPS / elapsed,
        "energy": np.max(np.abs(energy / energy[:, :1] - 1), axis=1),
        "casimir": np.max(np.abs(casimir / casimir[:, :1] - 1), axis=1),
    }


results = {(name, dtype): run(integ, dtype)
           for name, integ in INTEGRATORS.items() for dtype in ("float64", "float32")}
print(f"{'integrator':<15}{'dtype':>9}{'body-steps/s':>14}{'median Casimir err':>20}{'max Casimir err':>17}"
      f"{'median energy err':>19}{'max energy err':>16}")
for (name, dtype), r in results.items():
    print(f"{name:<15}{dtype:>9}{r['rate']:>14.3g}{np.median(r['casimir']):>20.2e}{r['casimir'].max():>17.2e}"
          f"{np.median(r['energy']):>19.2e}{r['energy'].max():>16.2e}")

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
bins = np.logspace(-17, -1, 80)
for (name, dtype), r in results.items():
    style = "-" if dtype == "float64" else ":"
    axes[0].hist(np.maximum(r["casimir"], 1e-17), bins=bins, histtype="step", ls=style, label=f"{name}, {dtype}")
    axes[1].hist(np.maximum(r["energy"], 1e-17), bins=bins, histtype="step", ls=style, label=f"{name}, {dtype}")
for ax, what in zip(axes, ("Casimir $|\\Pi|^2$", "energy")):
    ax.set_xscale("log")
    ax.set_xlabel(f"max relative {what} error over the run")
    ax.set_ylabel("bodies")
axes[0].set_title("Casimir: round-off for every body")
axes[1].set_title(f"energy: bounded, $O(h^2)$ (h = {H})")
axes[1].legend(fontsize=7)
plt.tight_layout()
plt.show()

# %% [markdown]
# The Casimir $|\Pi|^2$ is kept to round-off by every body: the DLP update (3.3) is a
# rotation of $\Pi$, whatever the Newton residual. For DEP the energy error is set by the
# discretisation, $O(h^2)$, bounded, with no drift, and is the same in float32 and float64.
# Moser–Veselov keeps this energy to round-off as well (as Hairer–Vilmart note for the
# discrete Moser–Veselov algorithm). The explicit Lie–Poisson splitting (five exact axis
# rotations per step, no Newton solve) is a Poisson map too, so its Casimir error is
# round-off; its energy error is $O(h^2)$ and bounded like DEP's. In float32 the
# Casimir error is round-off of the single-precision rotation, up to about $10^{-4}$ for the
# worst of $10^5$ bodies over 2000 steps (table above; it can grow like the number of steps
# times $\varepsilon_{32} \approx 1.2\cdot10^{-7}$): float32 is good for statistics over many bodies at
# $h$ where the $O(h^2)$ error dominates, not for studying conservation to round-off.

# %%
for (name, dtype), r in results.items():
    # float32: the rotation F is orthogonal to ~eps32 per step, so the Casimir error can
    # grow like steps × eps32 in the worst body (~8 eps32 per step allowed).
    bound = 1e-13 if dtype == "float64" else N_STEPS * 1e-6
    assert r["casimir"].max() < bound, (name, dtype, r["casimir"].max())
    assert r["energy"].max() < 0.05, (name, dtype)  # O(h²) with h = 0.05, no drift

# %% [markdown]
# ## 2. The intermediate-axis (Dzhanibekov) flip across a batch
#
# Bodies with $I = (1, 2, 3)$ spinning about the intermediate axis with a small perturbation
# $\varepsilon$ of the momentum, $\Pi_0 = (\varepsilon, 1, \varepsilon)$ normalised, for
# $\varepsilon$ spread over eight decades. The rotation about axis 2 is unstable; each body
# flips over periodically. Linearising Euler's equations about $\Pi = (0, p, 0)$ gives growth
# at the rate $\lambda = p\sqrt{(1/I_1 - 1/I_2)(1/I_2 - 1/I_3)}$, so the time to the first flip
# grows like $\lambda^{-1}\log(1/\varepsilon)$. One batched run gives every body's flip time.

# %%
I_FLIP = np.array([1.0, 2.0, 3.0])
eps = np.logspace(-10, -2, N_FLIP)
m_flip = np.stack([eps, np.ones_like(eps), eps], axis=1)
m_flip /= np.linalg.norm(m_flip, axis=1, keepdims=True)
n_flip = int(round(100 / H))
sol = lievi.simulate_batch(lievi.RigidBody(jnp.asarray(I_FLIP)), lievi.DEP(),
                           jnp.broadcast_to(jnp.eye(3), (N_FLIP, 3, 3)), jnp.asarray(m_flip),
                           h=H, n_steps=n_flip, save=lievi.Save(g=False, stats=False))
pi2 = np.asarray(sol.m[:, :, 1])
t = np.asarray(sol.ts[0])
first_flip = np.array([t[np.argmax(p < 0)] if np.any(p < 0) else np.nan for p in pi2])

p = 1.0
lam = p * np.sqrt((1 / I_FLIP[0] - 1 / I_FLIP[1]) * (1 / I_FLIP[1] - 1 / I_FLIP[2]))
ok = np.isfinite(first_flip)
slope = np.polyfit(np.log(1 / eps[ok]), first_flip[ok], 1)[0]
print(f"{ok.sum()} of {N_FLIP} bodies flipped within T = {n_flip * H:g}")
print(f"d(first flip time)/d log(1/eps): fitted {slope:.4f}, linear theory 1/lambda = {1 / lam:.4f}")
assert abs(slope * lam - 1) < 0.05

# %%
fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
for k in np.linspace(0, N_FLIP - 1, 6).astype(int):
    axes[0].plot(t, pi2[k], lw=1, label=f"ε = {eps[k]:.0e}")
axes[0].set_xlabel("t")
axes[0].set_ylabel(r"$\Pi_2$")
axes[0].set_title("Dzhanibekov flips, I = (1, 2, 3)")
axes[0].legend(fontsize=7, loc="lower left")
axes[1].semilogx(eps, first_flip, ".", ms=3, label="DEP, one batched run")
axes[1].semilogx(eps, first_flip[ok][0] + (np.log(1 / eps) - np.log(1 / eps[ok][0])) / lam, "k--",
                 lw=1, label=r"slope $1/\lambda$ (linear theory)")
axes[1].set_xlabel(r"perturbation $\varepsilon$")
axes[1].set_ylabel("time of the first flip")
axes[1].legend()
plt.tight_layout()
plt.show()

# %% [markdown]
# ## 3. Failures are per body
#
# Three bodies get a step size far too large for the exponential chart (rotation angle per
# step beyond π). With `throw=False` they report `RESULTS.step_too_large` (or a Newton
# failure) and their state is NaN from the failed step on; the other bodies are untouched —
# equal to a run without the failing bodies.

# %%
B = 8
h = np.full(B, 0.1)
h[[1, 4, 6]] = 50.0
body = lievi.RigidBody(jnp.array([2.0, 1.0, 2 / 3]))
m_fail = jnp.asarray(np.random.default_rng(1).normal(size=(B, 3)))
g_fail = jnp.broadcast_to(jnp.eye(3), (B, 3, 3))
sol = lievi.simulate_batch(body, lievi.DEP(), g_fail, m_fail, h=jnp.asarray(h), n_steps=20, throw=False)
for b in range(B):
    code_ = int(sol.result[b])
    print(f"body {b}: h = {h[b]:5.1f}  result {code_} {'ok' if code_ == 0 else lievi.RESULTS.message(code_)[:60] + '…'}"
          f"  failed_step {int(sol.stats['failed_step'][b])}")
good = h < 1
alone = lievi.simulate_batch(body, lievi.DEP(), g_fail[good], m_fail[good], h=jnp.asarray(h[good]), n_steps=20)
assert np.all(np.asarray(sol.result)[good] == 0) and np.all(np.asarray(sol.result)[~good] != 0)
np.testing.assert_allclose(sol.m[good], alone.m, rtol=0, atol=1e-13)

# %% [markdown]
# **Scaling out.** `lievi.shard_batch((bodies, g0, m0, h))` places the batch across all local
# devices (a one-axis `Mesh` and `NamedSharding`); `simulate_batch` on those inputs runs
# sharded, equal to the single-device run (`tests/test_batch.py`). Throughput against batch
# size on CPU and GPU: `benchmarks/throughput.py` and the README.
