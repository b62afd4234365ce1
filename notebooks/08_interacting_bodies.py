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
# # 08 — Interacting rigid bodies: a binary asteroid and rigid molecules
#
# `lievi.RigidBodies` is N rigid bodies on $SE(3)^N$ coupled by a potential of their poses.
# A kick integrator steps it as a half kick of every body by its wrench, the free step of
# each body (the method's own step of one body, the N bodies at once), and a half kick
# (the guide "Interacting rigid bodies", `docs/rigid-bodies.md`). Two systems:
#
# 1. **A binary asteroid** (`lievi.gravitating_bodies`): two bodies of three point masses
#    each in mutual gravity, the full two-body problem. A coupling of the relative poses
#    leaves the total linear and angular momentum conserved by the discrete flow (discrete
#    Noether theorem, paper §2); the energy stays bounded. Orbit and attitude exchange
#    angular momentum through the bodies' shapes.
# 2. **A box of rigid three-site molecules** (water-like: Lennard-Jones between the "O"
#    sites, Coulomb between all sites of different molecules): the energy error against
#    the step size, on the system that `benchmarks/rigid_molecules_jaxmd.py` compares
#    with jax-md's rigid-body NVE (built here from scratch).

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")
N_BINARY = 10_000 if SMALL else 100_000  # steps of the binary (h = 0.01)
N_MOLECULES = 200 if SMALL else 1_000  # steps per step size of the molecules

# %%
import json
import time
from pathlib import Path

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)
import lievi
from lievi import diagnostics as dg

# %% [markdown]
# ## 1. A binary asteroid
#
# Two bodies of three point masses (`masses` `(2, 3)`, `points` `(2, 3, 3)`);
# `gravitating_bodies` moves each body's points to their centre of mass and takes its mass
# and inertia from them. A near-circular mutual orbit at distance 1.5, both bodies spinning
# about generic axes. `DEP(chart="cayley")`, $h = 0.01$ (an orbit takes about 620 steps).

# %%
masses = jnp.array([[1.0, 0.6, 0.8], [0.5, 0.4, 0.3]])
points = jnp.asarray(np.random.default_rng(2).uniform(-1, 1, size=(2, 3, 3)) * 0.15)
binary = lievi.gravitating_bodies(1.0, masses, points)
mass = binary.mass
distance = 1.5
x = distance * jnp.array([-mass[1], mass[0]]) / jnp.sum(mass)  # barycentre at the origin
rotations = [lievi.SO3.exp(jnp.asarray(w)) for w in np.random.default_rng(3).normal(size=(2, 3))]
g0 = jnp.stack(
    [
        lievi.SE3.from_rotation_translation(R, jnp.array([xi, 0.0, 0.0]))
        for R, xi in zip(rotations, x)
    ]
)
speed = jnp.sqrt(jnp.sum(mass) / distance)
velocity = jnp.array([[0.0, -speed * mass[1], 0.0], [0.0, speed * mass[0], 0.0]]) / jnp.sum(mass)
P = jnp.einsum("nji,nj->ni", g0[:, :3, :3], mass[:, None] * velocity)  # body frame
Pi = jnp.einsum(
    "nij,nj->ni", binary.tensor[:, :3, :3], jnp.array([[0.3, 0.5, 1.0], [1.0, -0.5, 0.2]])
)
m0 = jnp.concatenate([Pi, P], axis=1)

start = time.perf_counter()
sol = lievi.simulate(
    binary, lievi.DEP(chart="cayley"), g0, m0, h=0.01, n_steps=N_BINARY, save=lievi.Save(every=100)
)
jax.block_until_ready(sol.m)
print(f"{N_BINARY} steps in {time.perf_counter() - start:.1f} s (compilation included)")
assert sol.result == lievi.RESULTS.successful

# %% [markdown]
# The total momentum $J = \sum_i \operatorname{Ad}^*_{g_i^{-1}} m_i$ — the angular
# momentum about the origin and the linear momentum — and the energy. The angular momentum
# splits into the bodies' **spin** $\sum_i R_i\Pi_i$ and their **orbital** part
# $\sum_i p_i \times R_i P_i$: the gravity gradient on the bodies' shapes (their
# quadrupoles) moves angular momentum between them, while the sum stays at round-off.

# %%
total = dg.total_momentum(binary, sol.g, sol.m)  # (T, 6)
energy = dg.energy(binary, sol.g, sol.m)
R, p = sol.g[:, :, :3, :3], sol.g[:, :, :3, 3]
spin = jnp.einsum("tnij,tnj->ti", R, sol.m[:, :, :3])
orbital = jnp.sum(jnp.cross(p, jnp.einsum("tnij,tnj->tni", R, sol.m[:, :, 3:])), axis=1)

momentum_drift = float(jnp.max(jnp.abs(total - total[0])) / jnp.max(jnp.abs(total[0])))
energy_error = float(jnp.max(jnp.abs(energy - energy[0])) / jnp.abs(energy[0]))
exchanged = float(jnp.max(jnp.linalg.norm(spin - spin[0], axis=1)))
print(f"total momentum: max drift {momentum_drift:.1e} (relative)")
print(f"energy: max relative error {energy_error:.1e}")
print(f"spin ↔ orbit: up to {exchanged:.2e} of angular momentum exchanged (|J| = "
      f"{float(jnp.linalg.norm(total[0, :3])):.3f})")  # fmt: skip
assert momentum_drift <= 1e-11
assert energy_error <= 5e-4
assert exchanged > 1e6 * momentum_drift * float(jnp.linalg.norm(total[0, :3]))

# First half against second half: bounded, no drift (a linear drift gives 3×).
error = jnp.abs(energy - energy[0])
half = len(error) // 2
ratio = float(error[half:].mean() / error[1:half].mean())
print(f"mean energy error, second half / first half: {ratio:.2f}")
assert ratio <= 2.0

# %%
t = sol.ts
fig, axes = plt.subplots(1, 3, figsize=(14, 3.6))
axes[0].plot(t, (energy - energy[0]) / jnp.abs(energy[0]), lw=0.6)
axes[0].set(xlabel="t", ylabel="(E − E₀)/|E₀|", title="energy: bounded")
axes[1].semilogy(t[1:], jnp.max(jnp.abs(total - total[0]), axis=1)[1:] + 1e-18, lw=0.6)
axes[1].set(xlabel="t", ylabel="max |J − J₀|", title="total momentum: round-off")
axes[2].plot(t, spin[:, 2] - spin[0, 2], label="spin Σ RΠ (z)")
axes[2].plot(t, orbital[:, 2] - orbital[0, 2], "--", label="orbital Σ p × RP (z)")
axes[2].set(xlabel="t", title="orbit–attitude exchange")
axes[2].legend()
plt.tight_layout()

# %% [markdown]
# ## 2. Rigid three-site molecules
#
# Eight water-like molecules (O of mass 16 and two H of mass 1, O–H 0.33, 104.5°;
# charges −0.8, +0.4, +0.4) on a jittered lattice in free space, random orientations and
# momenta: `lievi.SitePotential` with `LennardJones` between O sites ($\varepsilon = \sigma
# = 1$) and `Coulomb` between all sites of different molecules, no cut-off.
#
# The recipe: the sites of one molecule about its centre of mass, turned to its principal
# frame (`RigidBodies` takes principal moments; the sites are then given in that frame),
# each site counted as a small sphere of radius 0.5 (`2/5 r² m` added to each moment, as
# jax-md's `rigid_body.point_union_shape` does, so that the system is the one
# `benchmarks/rigid_molecules_jaxmd.py` runs in both libraries); the poses
# `g = [[R, x], [0, 1]]` from centres and unit quaternions, and `m = (Π, P)` with `Π` the
# body angular momentum and `P = Rᵀp` the linear momentum in the body frame.

# %%
STEP_SIZES = (0.0025, 0.005, 0.01, 0.02)
half, bond = np.deg2rad(104.5) / 2, 0.33
sites = np.array([[0.0, 0.0, 0.0], [bond * np.sin(half), bond * np.cos(half), 0.0],
                  [-bond * np.sin(half), bond * np.cos(half), 0.0]])  # fmt: skip
site_masses, charges = np.array([16.0, 1.0, 1.0]), np.array([-0.8, 0.4, 0.4])
sites -= site_masses @ sites / site_masses.sum()  # about the centre of mass
sphere = 2 / 5 * 0.5**2
tensor = sum(m * ((s @ s + sphere) * np.eye(3) - np.outer(s, s)) for m, s in zip(site_masses, sites))
moments, axes = np.linalg.eigh(tensor)
sites = sites @ axes  # in the principal frame

n = 8  # on a jittered 2×2×2 lattice of spacing 1.6, random orientations and momenta
rng = np.random.default_rng(0)
grid = np.stack(np.meshgrid(*[np.arange(2)] * 3, indexing="ij"), -1).reshape(-1, 3)
centres = 1.6 * grid + rng.uniform(-0.1, 0.1, size=(n, 3))
q = rng.normal(size=(n, 4))
q /= np.linalg.norm(q, axis=1, keepdims=True)  # unit quaternions (w, x, y, z)
angular = rng.normal(size=(n, 3)) * 0.5  # body angular momenta
linear = rng.normal(size=(n, 3))  # world linear momenta, total zero
linear -= linear.mean(axis=0)

pairs = lievi.SitePotential(
    np.broadcast_to(sites, (n, 3, 3)),
    (lievi.LennardJones(epsilon=[[1.0, 0.0], [0.0, 0.0]], sigma=1.0), lievi.Coulomb()),
    types=np.tile([0, 1, 1], (n, 1)),  # type 0: O, type 1: H (no Lennard-Jones)
    charges=np.tile(charges, (n, 1)),
)
molecules = lievi.RigidBodies(np.tile(moments, (n, 1)), np.full(n, site_masses.sum()), pairs)
R = jax.vmap(lievi.quaternion_wxyz_to_matrix)(jnp.asarray(q))
g0_mol = jnp.broadcast_to(jnp.eye(4), (n, 4, 4)).at[:, :3, :3].set(R).at[:, :3, 3].set(centres)
m0_mol = jnp.concatenate([jnp.asarray(angular), jnp.einsum("nji,nj->ni", R, linear)], axis=1)

# %%
errors = {}
for name, method in (
    ("DEP Cayley", lievi.DEP(chart="cayley")),
    ("splitting", lievi.LiePoissonSplitting()),
):
    errors[name] = []
    for h in STEP_SIZES:
        run = lievi.simulate(molecules, method, g0_mol, m0_mol, h=h, n_steps=N_MOLECULES)
        assert run.result == lievi.RESULTS.successful
        e = dg.energy(molecules, run.g, run.m)
        errors[name].append(float(jnp.max(jnp.abs(e - e[0])) / jnp.abs(e[0])))
    print(name, ", ".join(f"h={h:g}: {err:.2e}" for h, err in zip(STEP_SIZES, errors[name])))
    assert all(np.isfinite(errors[name])) and errors[name][-1] > errors[name][0]

# %%
fig, ax = plt.subplots(figsize=(6, 4))
for name, errs in errors.items():
    ax.loglog(STEP_SIZES, errs, "o-", label=f"lievi {name}")
# jax-md's figures for the same molecules, where the repository's benchmark results are at hand.
places = (Path.cwd().parent, Path.cwd())  # from `notebooks/` (as the tests run it) or the root
saved = [p / "benchmarks/results/rigid_molecules_jaxmd.json" for p in places]
saved = next((p for p in saved if p.exists()), None)
if saved is not None:
    document = json.loads(saved.read_text())
    if document["steps"] == N_MOLECULES:
        rows = [r for r in document["rows"] if r["method"].startswith("jax-md")]
        ax.loglog([r["h"] for r in rows], [r["relative_energy_error"] for r in rows], "k^:",
                  label="jax-md NVE (benchmark run)")  # fmt: skip
ax.set(xlabel="step size h", ylabel="max |E − E₀| / |E₀|",
       title=f"8 rigid three-site molecules, {N_MOLECULES} steps")  # fmt: skip
ax.legend()
plt.tight_layout()
