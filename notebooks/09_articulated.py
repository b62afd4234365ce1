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
# # 09 — Articulated bodies: a triple pendulum, a satellite's slew, link masses
#
# `lievi.ArticulatedBodies` joins rigid bodies by ball and hinge joints in a tree; each
# body keeps its own pose on SE(3) and the joints are holonomic constraints, enforced by
# `lievi.RATTLE` with discrete Lagrange multipliers at position and velocity level
# (docs/articulated.md). This notebook shows
#
# 1. a triple spherical pendulum: its energy under RATTLE against MuJoCo's integrators at
#    the same step;
# 2. a satellite with two hinged panels slewed rest to rest by `solve_optimal_control`;
# 3. the link masses of the pendulum identified from observed poses by `fit_system`.

# %% [markdown]
# **Sizes.** With `LIEVI_NOTEBOOK_SMALL=1` (as the test suite does) the notebook runs at a
# small size; the stored outputs are from a full-size run.

# %% tags=["parameters"]
import os

import jax

jax.config.update("jax_enable_x64", True)
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

import lievi

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL") == "1"
N_ENERGY = 2_000 if SMALL else 100_000  # steps of the energy comparison
H = 0.005

# %% [markdown]
# ## 1. The triple spherical pendulum
#
# Three rods (solid cylinders) hang end to end from a pivot at the origin, joined by ball
# joints. `place` puts the bodies so that their joint points coincide; `momentum` turns
# world angular velocities into momenta that satisfy the joints' velocity constraints.

# %%
def rod(mass, length, radius=0.2):
    side = mass * (3 * radius**2 + length**2) / 12
    return jnp.array([side, side, mass * radius**2 / 2])


masses, lengths = jnp.array([1.0, 0.8, 0.6]), jnp.array([1.0, 0.8, 0.7])
up = jnp.array([0.0, 0.0, 1.0])
joints = [lievi.BallJoint(jnp.zeros(3), up * lengths[0] / 2)] + [
    lievi.BallJoint(-up * lengths[i - 1] / 2, up * lengths[i] / 2) for i in (1, 2)
]
inertia = jnp.stack([rod(m, ell) for m, ell in zip(masses, lengths)])
pendulum = lievi.ArticulatedBodies(inertia, masses, [-1, 0, 1], joints, gravity=9.81)
R0 = lievi.SO3.exp(jnp.array([[0.6, 0.2, 0.0], [0.9, -0.4, 0.3], [-0.3, 1.1, -0.2]]))
w0 = jnp.array([[0.0, 0.5, 0.3], [0.8, 0.0, -0.4], [-0.3, 1.0, 0.5]])
g0 = pendulum.place(R0)
m0 = pendulum.momentum(g0, w0)

sol = lievi.simulate(pendulum, lievi.RATTLE(), g0, m0, h=H, n_steps=N_ENERGY, save=lievi.Save(every=10))
energy = lievi.diagnostics.energy(pendulum, sol.m, sol.g)
E0 = float(energy[0])
print("largest joint defect (relative to the link length):",
      float(jnp.max(jax.vmap(pendulum.joint_defect)(sol.g))))  # fmt: skip
lz = lievi.diagnostics.total_momentum(pendulum, sol.g, sol.m)[:, 2]
print("vertical angular momentum, largest change:", float(jnp.max(jnp.abs(lz - lz[0]))))
assert float(jnp.max(jax.vmap(pendulum.joint_defect)(sol.g))) <= 1e-12
assert float(jnp.max(jnp.abs(lz - lz[0]))) <= 1e-12 * float(jnp.max(jnp.abs(m0)))

# %% [markdown]
# The same pendulum in MuJoCo: joint coordinates (a quaternion per ball joint), each
# body's frame at its centre of mass; its energy is MuJoCo's own (`energy` flag). The
# initial joint coordinates are the relative rotations and angular velocities of the
# lievi state.

# %%
try:
    import mujoco
except ImportError:
    mujoco = None
    print("mujoco is not installed: the comparison is skipped")


def mjcf(integrator):
    xml = ""
    for i in reversed(range(3)):
        joint = pendulum.joints[i]
        pos = " ".join(map(str, np.asarray(joint.parent_point - joint.child_point)))
        anchor = " ".join(map(str, np.asarray(joint.child_point)))
        moments = " ".join(map(str, np.asarray(inertia[i])))
        xml = (f'<body pos="{pos}"><joint type="ball" pos="{anchor}"/><inertial pos="0 0 0" '
               f'mass="{float(masses[i])}" diaginertia="{moments}"/>{xml}</body>')  # fmt: skip
    return f"""<mujoco><option timestep="{H}" integrator="{integrator}" gravity="0 0 -9.81">
      <flag energy="enable"/></option><worldbody>{xml}</worldbody></mujoco>"""


def mujoco_energy(integrator):
    model = mujoco.MjModel.from_xml_string(mjcf(integrator))
    data = mujoco.MjData(model)
    R = np.asarray(g0[:, :3, :3])
    w = np.einsum("nij,nj->ni", R, np.asarray(pendulum.velocity(m0))[:, :3])
    parents = [np.eye(3), R[0], R[1]]
    parent_w = [np.zeros(3), w[0], w[1]]
    for i in range(3):
        relative = parents[i].T @ R[i]
        data.qpos[4 * i : 4 * i + 4] = np.asarray(lievi.matrix_to_quaternion_wxyz(relative))
        data.qvel[3 * i : 3 * i + 3] = R[i].T @ (w[i] - parent_w[i])
    mujoco.mj_forward(model, data)
    out = []
    for k in range(N_ENERGY):
        if k % 10 == 0:
            out.append(data.energy.sum())
        mujoco.mj_step(model, data)
    return np.array(out)


t = np.asarray(sol.ts)
plt.figure(figsize=(7, 3.5))
plt.semilogy(t, np.abs(np.asarray(energy) - E0) / abs(E0) + 1e-17, label="lievi RATTLE")
if mujoco is not None:
    for integrator in ("RK4", "implicitfast"):
        e = mujoco_energy(integrator)
        print(f"MuJoCo {integrator}: energy at t = 0 {e[0]:.12f}, lievi {E0:.12f}")
        plt.semilogy(t[: len(e)], np.abs(e - e[0]) / abs(e[0]) + 1e-17, label=f"MuJoCo {integrator}")
plt.xlabel("t")
plt.ylabel("relative energy error")
plt.title(f"triple spherical pendulum, h = {H}")
plt.legend()
plt.show()
half = len(energy) // 2
first, second = (float(jnp.mean(jnp.abs(e - E0))) for e in (energy[:half], energy[half:]))
print(f"RATTLE mean energy error, first half {first:.2e}, second half {second:.2e}")
assert second <= 1.5 * first

# %% [markdown]
# ## 2. A satellite slews with its panels
#
# A floating base (a box) with two panels on hinges, one on each side: a tree whose root
# has two children. `solve_optimal_control` finds the wrenches of least effort (a
# `(N, 6)` body-frame wrench per step and body: a torque about a hinge is `+τ n` on the
# panel and `−τ n` on the base) that turn the base by 0.6 rad about its vertical and fold
# the panels in, from rest to rest, with exact gradients through every Newton solve of
# RATTLE.

# %%
e2 = jnp.array([0.0, 1.0, 0.0])
side, reach = jnp.array([0.5, 0.0, 0.0]), jnp.array([0.6, 0.0, 0.0])
satellite = lievi.ArticulatedBodies(
    jnp.array([[1.0, 1.2, 0.8], [0.02, 0.05, 0.07], [0.02, 0.05, 0.07]]),
    jnp.array([5.0, 0.5, 0.5]),
    [-1, 0, 0],
    [None, lievi.HingeJoint(side, -reach, e2), lievi.HingeJoint(-side, reach, e2)],
)


def pose(turn, fold):
    base = lievi.SO3.exp(jnp.array([0.0, 0.0, turn]))
    R = [base, base @ lievi.SO3.exp(fold * e2), base @ lievi.SO3.exp(-fold * e2)]
    return satellite.place(jnp.stack(R))


n_steps, h_slew = (10, 0.2) if SMALL else (40, 0.05)
start, goal = pose(0.0, 0.0), pose(0.6, 0.5)
rest = jnp.zeros((3, 6))
# A small nonzero first guess: from rest with zero controls the gradient is not finite yet.
u0 = jnp.full((n_steps, 3, 6), 1e-3)
slew = lievi.solve_optimal_control(
    satellite, lievi.RATTLE(), start, rest, (goal, rest), n_steps, h_slew, u0=u0, tol=1e-9
)
print("converged:", slew.converged, " terminal violation:", slew.constraint_violation)
assert slew.converged
final = slew.solution.g[-1]
print("base turn reached:", float(lievi.SO3.log(final[0, :3, :3])[2]))

fig, ax = plt.subplots(1, 2, figsize=(10, 3.5))
ts = np.arange(n_steps) * h_slew
for i, name in enumerate(("base", "panel 1", "panel 2")):
    ax[0].plot(ts, np.linalg.norm(np.asarray(slew.controls[:, i, :3]), axis=-1), label=name)
ax[0].set(xlabel="t", ylabel="|torque|", title="optimal torques")
ax[0].legend()
turn = [float(lievi.SO3.log(g[0, :3, :3])[2]) for g in slew.solution.g]
ax[1].plot(np.arange(n_steps + 1) * h_slew, turn)
ax[1].set(xlabel="t", ylabel="base turn (rad)", title="the slew")
plt.show()

# %% [markdown]
# ## 3. Link masses from observed poses
#
# The pendulum's poses, observed every 5 steps, and a model whose masses are 20 % off:
# `fit_system` fits the masses (`params=lambda s: s.bodies.mass`; gravity weighs the same
# leaf) by L-BFGS with gradients through the RATTLE run.

# %%
n_obs = 8 if SMALL else 40
observed = lievi.simulate(pendulum, lievi.RATTLE(), g0, m0, h=0.01, n_steps=5 * n_obs)
guess = lievi.ArticulatedBodies(inertia, 1.2 * masses, [-1, 0, 1], joints, gravity=9.81)
fit = lievi.fit_system(
    guess, observed.g[::5], h=0.01, sample_every=5, params=lambda s: s.bodies.mass,
    m0=m0, g0=g0, integrator=lievi.RATTLE(), max_iters=100,
)  # fmt: skip
print("true masses:  ", np.asarray(masses))
print("fitted masses:", np.asarray(fit.system.mass))
assert np.allclose(np.asarray(fit.system.mass), np.asarray(masses), rtol=1e-6)
