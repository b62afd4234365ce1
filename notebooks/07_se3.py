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
# # 07 — Rigid bodies on SE(3): free fall, Kirchhoff's equations, a satellite in orbit
#
# `lievi.SE3` (rigid motions, twists ordered $(\omega, v)$) and `lievi.RigidBodySE3` (kinetic
# energy $\tfrac12\xi^\top M \xi$ with a 6×6 tensor $M$), integrated by the discrete
# Euler–Poincaré method `lievi.DEP` through the closed forms of $\exp$, $\operatorname{dexp}^{-1}$
# on SE(3). Three bodies:
#
# 1. **A tumbling body in free fall** (`UniformGravitySE3`): the spatial linear momentum falls
#    by exactly $m\gamma h$ per step, the vertical angular momentum is conserved.
# 2. **An ellipsoid in an ideal fluid** (Kirchhoff's equations): translation along the axis
#    of largest mass coefficient is stable, along the others unstable (Lamb, *Hydrodynamics*
#    §124); the Casimirs $|P|^2$, $P\cdot\Pi$ stay at round-off.
# 3. **A satellite in orbit** (`full_body_problem`): orbit and attitude exchange angular
#    momentum through the gravity gradient; the total is conserved to round-off.

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")
N_FALL = 200  # steps of the free fall (h = 0.02)
N_FLUID = 1_000 if SMALL else 8_000  # steps of the Kirchhoff runs (h = 0.02)
N_ORBIT = 1_000 if SMALL else 20_000  # steps of the satellite (h = 0.01)

# %%
import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)
import lievi
from lievi import diagnostics as dg

SE3 = lievi.SE3

# %% [markdown]
# ## 1. A tumbling body in free fall
#
# Principal inertia $(1, 2, 3)$, mass 2, centre of mass $\rho$ off the body origin, spun about
# the intermediate axis (the Dzhanibekov flip) and thrown upwards.

# %%
rho = jnp.array([0.1, 0.0, 0.05])
falling = lievi.RigidBodySE3(
    jnp.array([1.0, 2.0, 3.0]), 2.0, potential=lievi.UniformGravitySE3(2.0, 9.81, rho)
)
m0 = falling.tensor @ jnp.array([0.01, 6.0, 0.01, 1.0, 0.0, 10.0])
h = 0.02
sol = lievi.simulate(falling, lievi.DEP(), SE3.identity(), m0, h=h, n_steps=N_FALL)
spatial = np.asarray(dg.spatial_momentum(falling, sol.g, sol.m))
t = np.asarray(sol.ts)
fall_error = np.max(np.abs(spatial[:, 5] - spatial[0, 5] + 2.0 * 9.81 * t))
print(f"vertical linear momentum vs P₀ − mγt: {fall_error:.1e}")
print(f"vertical angular momentum drift:      {dg.relative_drift(spatial[:, 2]):.1e}")
assert fall_error <= 1e-10 and dg.relative_drift(spatial[:, 2]) <= 1e-11

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
p = np.asarray(SE3.translation(sol.g))
axes[0].plot(p[:, 0], p[:, 2])
axes[0].set(xlabel="x", ylabel="z", title="trajectory of the body origin")
axes[1].plot(t, np.asarray(sol.m[:, :3]))
axes[1].set(xlabel="t", ylabel="Π", title="body angular momentum (tumbling)")
plt.tight_layout()

# %% [markdown]
# ## 2. An ellipsoid in an ideal fluid (Kirchhoff)
#
# $M = \operatorname{diag}(J_1, J_2, J_3, m_1, m_2, m_3)$ with mass coefficients
# $m_1 < m_2 < m_3$ (own mass plus added mass). Start translating along each principal axis
# with a tiny rotation: along axis 3 (largest $m$) the motion stays close to a steady
# translation; along axes 1 and 2 the body turns.

# %%
J, masses = jnp.array([1.0, 1.2, 1.5]), jnp.array([1.0, 2.0, 3.0])
ellipsoid = lievi.RigidBodySE3(tensor=jnp.diag(jnp.concatenate([J, masses])))
h = 0.02
fig, ax = plt.subplots(figsize=(6, 3.5))
for axis in range(3):
    P0 = jnp.zeros(3).at[axis].set(1.0)
    m0 = jnp.concatenate([jnp.array([1e-3, 1e-3, 1e-3]), P0])
    sol = lievi.simulate(ellipsoid, lievi.DEP(), SE3.identity(), m0, h=h, n_steps=N_FLUID, save=lievi.Save(every=10))
    casimir_drift = dg.relative_drift(dg.casimirs(ellipsoid, sol.m))
    momentum_drift = dg.relative_drift(dg.spatial_momentum(ellipsoid, sol.g, sol.m))
    angle = np.degrees(np.arccos(np.clip(np.abs(np.asarray(sol.m[:, 3 + axis])), 0, 1)))
    print(f"axis {axis + 1}: largest tilt of P from the axis {angle.max():6.1f}°, "
          f"Casimir drift {casimir_drift:.1e}, spatial momentum drift {momentum_drift:.1e}")
    assert casimir_drift <= 1e-12 and momentum_drift <= 1e-11
    if axis == 2:
        assert angle.max() < 1.0  # stable
    else:
        assert angle.max() > 10.0  # unstable
    ax.plot(np.asarray(sol.ts), angle, label=f"start along axis {axis + 1} (m = {masses[axis]:g})")
ax.set(xlabel="t", ylabel="angle of P from the start axis [°]", title="Kirchhoff: stable broadside translation")
ax.legend()
plt.tight_layout()

# %% [markdown]
# ## 3. A satellite in orbit: the full body problem
#
# Four point masses (size ≈ 0.1) on a near-circular orbit of radius 1 around a planet with
# $\mu = 1$, spinning about a generic axis. `CentralGravity` is invariant under rotations about
# the planet, so the total angular momentum $R\Pi + p \times RP$ is conserved; the gravity
# gradient moves angular momentum between the orbit ($p \times RP$) and the spin ($R\Pi$).

# %%
points = 0.3 * jnp.array([[0.3, 0, 0], [-0.3, 0, 0], [0, 0.1, 0.05], [0, -0.1, -0.05]])
satellite = lievi.full_body_problem(1.0, jnp.array([1.0, 1.0, 0.5, 0.5]), points)
R0 = lievi.SO3.exp(jnp.array([0.2, 0.1, 0.3]))
g0 = SE3.from_rotation_translation(R0, jnp.array([1.0, 0.0, 0.0]))
m0 = satellite.tensor @ jnp.concatenate([jnp.array([0.5, -0.3, 1.2]), R0.T @ jnp.array([0.0, 1.0, 0.0])])
h = 0.01
sol = lievi.simulate(satellite, lievi.DEP(), g0, m0, h=h, n_steps=N_ORBIT, save=lievi.Save(every=10))
total = np.asarray(dg.spatial_momentum(satellite, sol.g, sol.m))[:, :3]
R, p, P = np.asarray(sol.g[:, :3, :3]), np.asarray(sol.g[:, :3, 3]), np.asarray(sol.m[:, 3:])
orbital = np.cross(p, np.einsum("tij,tj->ti", R, P))
spin = total - orbital
energy = np.asarray(dg.energy(satellite, sol.g, sol.m))
print(f"total angular momentum drift: {dg.relative_drift(total):.1e}")
print(f"orbital angular momentum (z) ranges over {orbital[:, 2].min():.4f} … {orbital[:, 2].max():.4f}")
print(f"energy: relative error ≤ {np.max(np.abs(energy / energy[0] - 1)):.1e} (bounded)")
assert dg.relative_drift(total) <= 1e-11

fig, axes = plt.subplots(1, 2, figsize=(10, 3.5))
t = np.asarray(sol.ts)
axes[0].plot(t, orbital[:, 2] - orbital[0, 2], label="orbital")
axes[0].plot(t, spin[:, 2] - spin[0, 2], "--", label="spin")
axes[0].plot(t, total[:, 2] - total[0, 2], label="total")
axes[0].set(xlabel="t", ylabel="change of $L_z$", title="angular momentum exchange")
axes[0].legend()
axes[1].plot(p[:, 0], p[:, 1])
axes[1].set(xlabel="x", ylabel="y", title="orbit", aspect="equal")
plt.tight_layout()

# %% [markdown]
# The DEL residual, the order against DOP853 and the long-run conservation of these systems
# are checked in `tests/test_se3_body.py`; the group's closed forms in `tests/test_se3.py`;
# the per-step cost against SO(3) in `benchmarks/se3_step_cost.py`. See `docs/se3.md`.
