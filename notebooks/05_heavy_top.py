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
# # 05 — The heavy top and the 3-D pendulum: potentials and broken symmetry
#
# A rigid body with a fixed point in uniform gravity has the Lagrangian
# $L(g, \Omega) = \tfrac12 \Omega^\top I \Omega - m\gamma\, e_3\cdot(g\rho)$: the potential
# breaks the symmetry of the free body down to rotations about the vertical (the paper's §7,
# with the advected parameter $\Gamma = g^\top e_3$, the vertical seen from the body). In lievi
# it is `lievi.heavy_top(inertia, mass, center_of_mass, gravity)`, i.e.
# `lievi.RigidBody(inertia, potential=lievi.UniformGravity(...))`; the torque
# $m\gamma\,\Gamma\times\rho$ comes from the potential by autodiff, and every integrator takes
# it (the variational ones as half kick, free step, half kick).
#
# This notebook shows
#
# 1. the sleeping Lagrange top (stable above the critical spin, falling below it);
# 2. the nutating Lagrange top, with its three exact discrete conservation laws;
# 3. the chaotic asymmetric top, through a Poincaré section;
# 4. the energy behaviour of every integrator over long runs;
# 5. the 3-D (spherical) pendulum.

# %% [markdown]
# **Sizes.** With `LIEVI_NOTEBOOK_SMALL=1` (as the test suite does) the notebook runs at a
# small size; the stored outputs are from a full-size run.

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")

H = 0.02  # step size
N_TOP = 1_000 if SMALL else 5_000  # steps of the Lagrange-top runs (T = 20 or 100)
N_CHAOS = 4_000 if SMALL else 40_000  # steps per orbit of the Poincaré section
N_ORBITS = 3 if SMALL else 6
N_LONG = 2_000 if SMALL else 40_000  # steps of the energy comparison (h = 0.05)

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)
plt.rcParams["figure.dpi"] = 64  # small stored figures
import lievi
from lievi import diagnostics as dg


def vertical(sol):
    # Γ = gᵀe₃: the world's vertical in body coordinates (the advected parameter)
    return np.asarray(sol.g[:, 2, :])


# %% [markdown]
# ## 1. The sleeping top
#
# A symmetric top ($I_1 = I_2$, centre of mass on the symmetry axis at height $\ell$) spinning
# upright about its axis "sleeps" when the spin is fast enough, $\Pi_3^2 > 4 I_1 m\gamma\ell$
# (the Maxwell–Klein criterion): the upright state is then stable. Below it the top falls.
# Both runs start upright with a tiny transverse kick.

# %%
inertia = jnp.array([1.0, 1.0, 0.4])
mass, ell = 2.0, 0.6
top = lievi.heavy_top(inertia, mass, jnp.array([0.0, 0.0, ell]), gravity=1.0)
critical = np.sqrt(4 * inertia[0] * mass * ell)  # Π₃ at the stability threshold
fig, ax = plt.subplots(figsize=(7, 3.5), layout="constrained")
tilts = {}
for factor in (1.3, 0.7):
    m0 = jnp.array([1e-3, 0.0, factor * critical])
    sol = lievi.simulate(top, lievi.DEP(), jnp.eye(3), m0, h=H, n_steps=N_TOP, save=lievi.Save(every=5))
    tilt = np.degrees(np.arccos(np.clip(vertical(sol)[:, 2], -1, 1)))
    tilts[factor] = tilt
    ax.plot(sol.ts, tilt, label=f"Π₃ = {factor:g} × critical")
ax.set(xlabel="t", ylabel="tilt of the axis [deg]", title="sleeping top: stable above the critical spin")
ax.legend()
plt.show()
assert tilts[1.3].max() < 1.0  # stays upright
assert tilts[0.7].max() > 30.0  # falls

# %% [markdown]
# ## 2. The nutating Lagrange top
#
# Tilted and spinning, the axis of a Lagrange top precesses about the vertical and nods
# (nutation) between two tilts. The variational integrators are equivariant under the
# symmetry that is left — rotations about the vertical in space and about the figure axis in
# the body — so by the discrete Noether theorem they keep the vertical angular momentum
# $e_3\cdot(g\Pi) = \Pi\cdot\Gamma$ and the spin $\Pi_3$ exactly, and $|\Gamma|^2 = 1$ (the
# attitude stays a rotation), all to round-off.

# %%
g0 = lievi.SO3.exp(jnp.array([0.5, 0.0, 0.0]))  # axis tilted by 0.5 rad
m0 = jnp.array([0.0, 0.0, 2.5])
sol = lievi.simulate(top, lievi.DEP(), g0, m0, h=H, n_steps=N_TOP)
gamma, m = vertical(sol), np.asarray(sol.m)
axis_world = np.asarray(sol.g[:, :, 2])  # the figure axis in space
fig, axes = plt.subplots(1, 2, figsize=(11, 4), layout="constrained")
axes[0].plot(axis_world[:, 0], axis_world[:, 1], lw=0.7)
axes[0].set(aspect="equal", title="figure axis seen from above: precession + nutation", xlabel="x", ylabel="y")
drifts = {
    "|Γ|² − 1": np.abs(np.sum(gamma**2, 1) - 1),
    "Π·Γ": np.abs(np.sum(m * gamma, 1) - np.sum(m[0] * gamma[0])),
    "Π₃": np.abs(m[:, 2] - m[0, 2]),
    "energy": np.abs(np.asarray(dg.energy(top, sol.g, sol.m)) - float(dg.energy(top, g0, m0))),
}
for name, d in drifts.items():
    axes[1].semilogy(sol.ts[1:], np.maximum(d[1:], 1e-17), lw=0.8, label=name)
axes[1].set(xlabel="t", title="conservation (DEP): three laws to round-off, energy bounded")
axes[1].legend()
plt.show()
for name in ("|Γ|² − 1", "Π·Γ", "Π₃"):
    assert drifts[name].max() < 1e-12, name

# %% [markdown]
# ## 3. The asymmetric top: chaos in a Poincaré section
#
# With $I = (2, 1, 2/3)$ and an off-axis centre of mass the top is not integrable. The reduced
# dynamics lives on $(\Pi, \Gamma)$ with the Casimirs $|\Gamma|^2 = 1$ and $\Pi\cdot\Gamma$ fixed,
# and the energy: a 3-dimensional level set. A Poincaré section — every crossing of
# $\Pi_2 = 0$ upwards, plotted in $(\Gamma_1, \Gamma_2)$ — shows regular orbits as curves and
# chaotic ones as scattered clouds. Orbits are started with $\Pi\cdot\Gamma = 0$ from
# different tilts, with the splitting (explicit, symmetric) at $h = 0.02$.

# %%
asym = lievi.heavy_top(jnp.array([2.0, 1.0, 2 / 3]), 1.0, jnp.array([0.3, -0.2, 0.5]), gravity=1.0)


@jax.jit
def orbit(g0, m0):
    return lievi.simulate(asym, lievi.LiePoissonSplitting(), g0, m0, h=H, n_steps=N_CHAOS, throw=False)


fig, ax = plt.subplots(figsize=(6, 6), layout="constrained")
rng = np.random.default_rng(0)
for k in range(N_ORBITS):
    g0 = lievi.SO3.exp(jnp.asarray(rng.normal(size=3) * 0.8))
    gamma0 = np.asarray(g0[2])
    m0 = rng.normal(size=3)
    m0 = jnp.asarray(m0 - np.dot(m0, gamma0) * gamma0)  # Π·Γ = 0
    sol = orbit(g0, m0)
    assert int(sol.result) == 0
    gamma, m = vertical(sol), np.asarray(sol.m)
    up = np.flatnonzero((m[:-1, 1] < 0) & (m[1:, 1] >= 0))
    w = -m[up, 1] / (m[up + 1, 1] - m[up, 1])  # linear interpolation to Π₂ = 0
    section = gamma[up] * (1 - w[:, None]) + gamma[up + 1] * w[:, None]
    ax.plot(section[:, 0], section[:, 1], ".", ms=1.5)
    assert np.max(np.abs(np.sum(gamma**2, 1) - 1)) < 1e-12
    assert np.max(np.abs(np.sum(m * gamma, 1))) < 1e-12
ax.set(xlabel="Γ₁", ylabel="Γ₂", aspect="equal", title="Poincaré section Π₂ = 0 ↑ of the asymmetric top")
plt.show()

# %% [markdown]
# ## 4. Energy over long runs, every integrator
#
# Symplectic (variational or Lie–Poisson splitting) integrators keep the energy error bounded
# and oscillating, with no drift, for very long times (backward error analysis); the
# non-geometric RK4 drifts. Asymmetric top, $h = 0.05$.

# %%
g0 = lievi.SO3.exp(jnp.array([0.4, -0.3, 0.2]))
m0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
E0 = float(dg.energy(asym, g0, m0))
integrators = {
    "DEP exp": lievi.DEP(),
    "DEP Cayley": lievi.DEP(chart="cayley"),
    "Moser–Veselov": lievi.MoserVeselov(),
    "Lie–Poisson splitting": lievi.LiePoissonSplitting(),
    "Composition(DEP), order 4": lievi.Composition(lievi.DEP(), order=4),
    "RK4 (non-geometric)": lievi.RK4(),
}
every = N_LONG // 500
fig, ax = plt.subplots(figsize=(9, 4.5), layout="constrained")
errors = {}
for name, integrator in integrators.items():
    sol = lievi.simulate(asym, integrator, g0, m0, h=0.05, n_steps=N_LONG, save=lievi.Save(every=every))
    err = np.abs(np.asarray(dg.energy(asym, sol.g, sol.m)) - E0)
    errors[name] = err
    ax.loglog(sol.ts[1:], np.maximum(err[1:], 1e-17), lw=0.8, label=name)
ax.set(xlabel="t", ylabel="|E − E₀|", title="energy error over long runs (asymmetric heavy top, h = 0.05)")
ax.legend(fontsize="small")
plt.show()
for name, err in errors.items():
    tenth = len(err) // 10
    print(f"{name:28s} max |E − E₀| first tenth {err[:tenth].max():.2e}, last tenth {err[-tenth:].max():.2e}")
    if "RK4" not in name:  # bounded: no growth from the first to the last tenth
        assert err[-tenth:].max() <= 1.5 * err[:tenth].max() + 1e-13, name

# %% [markdown]
# ## 5. The 3-D pendulum
#
# A slender rod on a spherical joint — the inertia about the pivot, the centre of mass far
# from it — is a spherical pendulum with a spinning bob. The tip traces the familiar rosette;
# energy stays bounded, the attitude a rotation.

# %%
length, mass = 1.0, 1.0
inertia = jnp.array([mass * length**2 / 3, mass * length**2 / 3, 1e-2])
pendulum = lievi.heavy_top(inertia, mass, jnp.array([0.0, 0.0, -length / 2]), gravity=9.81)
g0 = lievi.SO3.exp(jnp.array([1.2, 0.3, 0.0]))  # swung out by ~70°
m0 = inertia * jnp.array([0.0, 1.0, 0.5])
sol = lievi.simulate(pendulum, lievi.DEP(), g0, m0, h=0.005, n_steps=2 * N_TOP)
tip = -length * np.asarray(sol.g[:, :, 2])  # the rod points along −e₃ in the body
energy = np.asarray(dg.energy(pendulum, sol.g, sol.m))
fig, axes = plt.subplots(1, 2, figsize=(11, 4.5), layout="constrained")
axes[0].plot(tip[:, 0], tip[:, 1], lw=0.6)
axes[0].set(aspect="equal", xlabel="x", ylabel="y", title="3-D pendulum: the tip seen from above")
axes[1].plot(sol.ts, (energy - energy[0]) / abs(energy[0]))
axes[1].set(xlabel="t", ylabel="(E − E₀)/|E₀|", title="relative energy error (DEP, h = 0.005)")
plt.show()
assert np.max(np.abs(energy - energy[0])) / abs(energy[0]) < 1e-3
assert float(jnp.max(dg.orthogonality_defect(pendulum, sol.g))) < 1e-12
