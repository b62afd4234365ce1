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
# # 01 — The free rigid body with the discrete Euler–Poincaré integrator
#
# This notebook runs `lievi`'s implementation of Marsden, Pekarsky & Shkoller, *Discrete
# Euler–Poincaré and Lie–Poisson equations*, Nonlinearity **12** (1999) 1647–1662, on the free
# rigid body, and shows three things:
#
# 1. **Polhodes.** The discrete momenta stay on the intersection of the momentum sphere
#    $|\Pi| = \text{const}$ (exactly) and the energy ellipsoid (up to a small bounded error).
# 2. **Long-time energy behaviour.** Over $10^5$ steps at $h = 0.1$ the energy error is
#    bounded and does not drift, for both the exponential and the Cayley chart; a standard
#    second-order method of the same order drifts.
# 3. **Convergence order.** Both charts converge with order 2. This answers the question the
#    paper leaves open at the end of §5: second order *does* survive without the Cayley map.
#
# The test problem is the Hairer–Lubich–Wanner rigid body: principal moments
# $I = (2, 1, 2/3)$, $\Pi_0 = (\cos 1.1, 0, \sin 1.1)$, $g_0 = I_3$.

# %% [markdown]
# **Sizes.** The parameter cell below sets the problem sizes. With the environment variable
# `LIEVI_NOTEBOOK_SMALL=1` (as the test suite does) the notebook runs at a small size in a
# few seconds; the stored outputs are from a full-size run.

# %% tags=["parameters"]
import os

SMALL = os.environ.get("LIEVI_NOTEBOOK_SMALL", "0") not in ("", "0")

H_LONG = 0.1  # step size of the long run (HLW)
N_LONG = 2_000 if SMALL else 100_000  # steps of the long run (T = N_LONG * H_LONG)
SAVE_EVERY = 10  # keep every 10th state of the long run (memory)
T_CONV = 2.0  # final time of the convergence study
HS = [0.1 / 2**k for k in range(3 if SMALL else 8)]  # step sizes of the convergence study
H_POLHODE, T_POLHODE = 0.05, 60.0  # polhodes

# %%
import time

import jax
import jax.numpy as jnp
import matplotlib.pyplot as plt
import numpy as np

jax.config.update("jax_enable_x64", True)  # float64: needed by the reference solution

import lievi
from lievi import diagnostics

# %config InlineBackend.figure_formats = ["png"]
plt.rcParams.update({"figure.dpi": 100, "axes.grid": True, "grid.alpha": 0.3})
print("lievi", lievi.__version__, "| jax", jax.__version__, "| devices", jax.devices())
print("SMALL =", SMALL, "| N_LONG =", N_LONG, "| HS =", HS)

# %% [markdown]
# ## The scheme
#
# The rigid body is the left-invariant system on $G = \mathrm{SO}(3)$ with reduced Lagrangian
# $l(\Omega) = \tfrac12 \Omega^\top I\,\Omega$, body momentum $\Pi = I\Omega$ and energy
# $H(\Pi) = \tfrac12 \Pi^\top I^{-1}\Pi$. Its Euler–Poincaré equations are Euler's equations
# $\dot\Pi = \Pi\times\Omega$ with the reconstruction $\dot g = g\,\hat\Omega$.
#
# `lievi.DEP` discretises it with the discrete Lagrangian (4.7),
# $L_d(g_k, g_{k+1}) = h\, l\big(\varphi^{-1}(F_k)/h\big)$ with the increment
# $F_k = g_k^{-1} g_{k+1}$ (the paper's $f_{k+1\,k} = F_k^{-1}$) and a chart $\varphi$ of the
# group. One step $(g_k, \Pi_k) \mapsto (g_{k+1}, \Pi_{k+1})$ is:
#
# | | equation | paper |
# |---|---|---|
# | **DEP** (implicit, Newton) | solve $\;\Pi_k = \mathrm{d}\varphi^{-1}(\xi_k)^{\top}\, I\,\xi_k/h\;$ for $\xi_k\in\mathfrak{so}(3)$, set $F_k = \varphi(\xi_k)$ | (4.8), momentum form |
# | **DLP** (explicit) | $\Pi_{k+1} = \mathrm{Ad}_{F_k}^{\top}\Pi_k = F_k^\top \Pi_k$ | (3.3) |
# | **reconstruction** (explicit) | $g_{k+1} = g_k F_k$ | (2.9) |
#
# - `DEP(chart="exp")`: $\varphi = \exp$, the paper's own discretisation (4.7)–(4.8).
#   $\mathrm{d}\exp^{-1}(\xi) = \sum_n \frac{B_n}{n!}\,\mathrm{ad}_\xi^n$ is the inverse of
#   $\mathrm{iex}(\mathrm{ad}_\xi)$ of (4.3); the paper's $\chi(\mathrm{ad}_\xi)$ is
#   $\mathrm{d}\exp^{-1}(-\xi)$. The paper writes (4.8), for right-invariant systems, as a
#   two-step recursion for $\xi_{k\,k+1} = \log f_{k\,k+1}$:
#   $\; l'(\xi_{k\,k+1}/h)\cdot\chi(\mathrm{ad}_{\xi_{k\,k+1}}) = l'(\xi_{k-1\,k}/h)\cdot\chi(\mathrm{ad}_{\xi_{k-1\,k}})\cdot\exp(\mathrm{ad}_{\xi_{k-1\,k}})$.
#   Its left-hand side is the discrete momentum at step $k$; naming it splits (4.8) into the
#   implicit equation for $\xi$ given the momentum and the explicit coadjoint update (DLP).
#   The table is the left-invariant mirror image, used for the rigid body.
# - `DEP(chart="cayley")`: $\varphi = \mathrm{cay}$, $\mathrm{cay}(\xi) = (1+\hat\xi/2)(1-\hat\xi/2)^{-1}$,
#   $\mathrm{d}\,\mathrm{cay}^{-1}(\xi) = I - \hat\xi/2 + \xi\xi^\top/4$. The Cayley map is
#   the one of the paper's closing remark in §5 on the Lewis–Simo algorithm (5.7)
#   (reconstruction (2.9), DLP (3.3) and DEP (5.4) of the Moser–Veselov discrete Lagrangian
#   $\mathrm{tr}(f\Lambda)$), which Lewis and Simo proved second order. It is not the same
#   scheme: on SO(3), $\mathrm{tr}\big((I - \mathrm{cay}(\xi))\Lambda\big)/h = \tfrac12\xi^\top I\xi \,/\, \big(h\,(1 + |\xi|^2/4)\big)$,
#   while `DEP(chart="cayley")` uses $\tfrac12\xi^\top I\xi/h$, so the iterates differ at
#   $O(h^3)$ per step. What both share is the chart, and what the open question asks is
#   whether the *exponential* chart, (4.7)–(4.8), keeps second order.
#
# Because $\Pi_{k+1}$ is obtained from $\Pi_k$ by a rotation, the Casimir $|\Pi|$ is
# conserved to round-off; the energy is not conserved exactly, but the map is Lie–Poisson
# (symplectic on each sphere), so by backward error analysis its energy error stays bounded,
# without drift, over very long times.

# %%
body = lievi.RigidBody(jnp.array([2.0, 1.0, 2.0 / 3.0]))
g0 = jnp.eye(3)
m0 = jnp.array([np.cos(1.1), 0.0, np.sin(1.1)])
CHARTS = {"exp": lievi.DEP(chart="exp"), "cayley": lievi.DEP(chart="cayley")}
COLORS = {"exp": "C0", "cayley": "C3"}

# %% [markdown]
# ## 1. Polhodes on the momentum sphere
#
# The continuous flow conserves the Casimir $|\Pi|^2$ and the energy $H(\Pi)$, so every
# momentum trajectory lies on the intersection of a sphere and an energy ellipsoid. Rotation
# about the largest ($\Pi_1$, $I_1 = 2$) and smallest ($\Pi_3$, $I_3 = 2/3$) axes is stable:
# the polhodes are closed loops around them. Rotation about the intermediate axis ($\Pi_2$)
# is unstable; its level set $H = |\Pi|^2/(2 I_2)$ is the *separatrix*, two great circles in
# the planes $\Pi_3 = \pm\sqrt{(1/I_2 - 1/I_1)/(1/I_3 - 1/I_2)}\;\Pi_1$ (dashed below).
#
# We integrate a dozen unit momenta — in the $\Pi_1\Pi_3$ plane on both sides of the
# separatrix, and two starting within $0.02$ of the intermediate axis — with the
# exponential-chart DEP, all at once with `jax.vmap`.

# %%
angles = [0.25, 0.55, 0.75, 1.0, 1.25, 1.5]  # polar angle in the Pi_1 Pi_3 plane (separatrix: pi/4)
starts = [[np.cos(a), 0.0, np.sin(a)] for a in angles]
starts += [[-np.cos(a), 0.0, np.sin(a)] for a in angles[1:-1]]
starts += [[0.02, 1.0, 0.0], [0.0, -1.0, 0.02]]  # near the intermediate axis
M0 = jnp.asarray([np.asarray(s) / np.linalg.norm(s) for s in starts])

n_polhode = int(round(T_POLHODE / H_POLHODE))


def polhode(m_start):
    sol = lievi.simulate(body, CHARTS["exp"], g0, m_start, h=H_POLHODE, n_steps=n_polhode,
                         throw=False)  # under vmap: failures are reported in sol.result
    return sol.m, sol.result


ms, results = jax.vmap(polhode)(M0)  # simulate is jit-compiled inside
assert bool(jnp.all(results == lievi.RESULTS.successful))
ms = np.asarray(ms)  # (n_bodies, T, 3)

casimir_err = np.max(np.abs(np.linalg.norm(ms, axis=-1) - 1.0))
energies = np.asarray(diagnostics.energy(body, None, jnp.asarray(ms)))
energy_err = np.max(np.abs(energies - energies[:, :1]) / energies[:, :1])
print(f"{len(M0)} bodies x {n_polhode} steps of h = {H_POLHODE}")
print(f"max | |Pi_k| - 1 |            = {casimir_err:.1e}   (Casimir: round-off)")
print(f"max |H(Pi_k) - H(Pi_0)|/H(Pi_0) = {energy_err:.1e}   (energy: O(h^2), bounded)")
assert casimir_err < 1e-12

# %%
inertia = np.array([2.0, 1.0, 2.0 / 3.0])
u, v = np.meshgrid(np.linspace(0, 2 * np.pi, 60), np.linspace(0, np.pi, 30))
sphere = (np.cos(u) * np.sin(v), np.sin(u) * np.sin(v), np.cos(v))
slope = np.sqrt((1 / inertia[1] - 1 / inertia[0]) / (1 / inertia[2] - 1 / inertia[1]))
s = np.linspace(0, 2 * np.pi, 400)
cmap, e_min, e_max = plt.get_cmap("viridis"), 0.5 / inertia[0], 0.5 / inertia[2]


def front_back(points, view):
    # split a curve into the part facing the viewer and the part behind the sphere
    front = points @ view > 0
    return np.where(front[:, None], points, np.nan), np.where(front[:, None], np.nan, points)


fig = plt.figure(figsize=(12, 6.5))
for i, (elev, azim) in enumerate([(25, 35), (25, 215)]):
    view = np.array([np.cos(np.radians(elev)) * np.cos(np.radians(azim)),
                     np.cos(np.radians(elev)) * np.sin(np.radians(azim)), np.sin(np.radians(elev))])
    ax = fig.add_subplot(1, 2, i + 1, projection="3d", computed_zorder=False)
    ax.plot_surface(*sphere, color="0.9", alpha=0.3, linewidth=0, zorder=0)
    for sign in (1, -1):  # the separatrix: great circles through the intermediate axis
        circle = np.stack([np.cos(s), np.sqrt(1 + slope**2) * np.sin(s), sign * slope * np.cos(s)])
        circle = circle.T
        circle /= np.linalg.norm(circle, axis=-1, keepdims=True)
        front, back = front_back(circle, view)
        ax.plot(*front.T, "k--", lw=1.0, zorder=3)
        ax.plot(*back.T, "k--", lw=0.6, alpha=0.15, zorder=1)
    for traj, e in zip(ms, energies[:, 0]):
        color = cmap((e - e_min) / (e_max - e_min))
        front, back = front_back(traj, view)
        ax.plot(*front.T, color=color, lw=1.8, zorder=4)
        ax.plot(*back.T, color=color, lw=1.0, alpha=0.2, zorder=1)
        if traj[0] @ view > 0:
            ax.plot(*traj[0], "o", color="k", ms=3, zorder=5)
    for k, name in enumerate(["$\\Pi_1$", "$\\Pi_2$", "$\\Pi_3$"]):
        tip = np.zeros(3)
        tip[k] = 1.3
        ax.plot(*np.stack([tip / 1.3, tip]).T, color="0.3", lw=1, zorder=5)
        ax.plot(*np.stack([-tip, -tip / 1.3]).T, color="0.3", lw=1, zorder=0)
        ax.text(*(1.05 * tip), name, fontsize=12, zorder=6)
    ax.view_init(elev=elev, azim=azim)
    ax.set(xlim=(-1, 1), ylim=(-1, 1), zlim=(-1, 1))
    ax.set_box_aspect((1, 1, 1), zoom=1.1)
    ax.set_axis_off()
fig.suptitle("Discrete polhodes (exp-chart DEP, h = %g): sphere $\\cap$ energy ellipsoid\n"
             "axes: $\\Pi_1$ largest, $\\Pi_2$ intermediate, $\\Pi_3$ smallest moment of inertia; "
             "colour: energy; dashed: separatrix; dots: initial momenta; faint: far side;\n"
             "left and right: the sphere seen from opposite sides" % H_POLHODE)
fig.subplots_adjust(left=0, right=1, bottom=0, top=0.88, wspace=0)
plt.show()


# %% [markdown]
# ## 2. Energy error over $10^5$ steps at $h = 0.1$
#
# The HLW problem is integrated for $10^5$ steps of $h = 0.1$ (to $t = 10^4$, several
# hundred rotations) with both charts, keeping every 10th state (`save=lievi.Save(every=10)`). For
# contrast, the same problem is integrated with the explicit midpoint rule (a second-order
# Runge–Kutta method, not symplectic) applied to Euler's equations.

# %%
def energy_error(m):
    E = np.asarray(diagnostics.energy(body, None, m))
    return np.abs(E - E[0]) / E[0]


long_runs = {}
for name, dep in CHARTS.items():
    start = time.perf_counter()
    sol = lievi.simulate(body, dep, g0, m0, h=H_LONG, n_steps=N_LONG, save=lievi.Save(every=SAVE_EVERY))
    sol.m.block_until_ready()
    long_runs[name] = (np.asarray(sol.ts), energy_error(sol.m),
                       np.asarray(sol.m), np.asarray(sol.g))
    seconds = time.perf_counter() - start
    print(f"DEP {name:6s}: {N_LONG} steps in {seconds:.1f} s (incl. compilation), "
          f"Newton iterations/step = {int(sol.stats['total_newton_iterations']) / N_LONG:.2f}")


@jax.jit
def explicit_midpoint(m_start):  # Euler's equations only; same order (2), not symplectic
    def f(m):
        return jnp.cross(m, body.velocity(m))

    def step(m, _):
        return m + H_LONG * f(m + 0.5 * H_LONG * f(m)), None

    def save(m, _):
        m, _ = jax.lax.scan(step, m, None, length=SAVE_EVERY)
        return m, m

    _, saved = jax.lax.scan(save, m_start, None, length=N_LONG // SAVE_EVERY)
    return jnp.concatenate([m_start[None], saved])


rk_m = np.asarray(explicit_midpoint(m0))
rk_err = energy_error(rk_m)


# %%
def envelope(t, err, window=100):
    # maximum of the error over consecutive windows of `window` saved points
    n = (len(err) - 1) // window * window
    return t[1:n + 1].reshape(-1, window).max(1), err[1:n + 1].reshape(-1, window).max(1)


fig, ax = plt.subplots(figsize=(11, 4.5))
ts = long_runs["exp"][0]
ax.semilogy(ts, rk_err, color="0.5", lw=1.5, label="explicit midpoint (RK2), not symplectic")
for name in ("cayley", "exp"):
    ax.semilogy(ts, long_runs[name][1], color=COLORS[name], lw=0.3, alpha=0.35)
    ax.semilogy(*envelope(ts, long_runs[name][1]), color=COLORS[name], lw=2,
                label=f"DEP, {name} chart (thin: every 10th step; thick: max over 1000 steps)")
ax.set_ylim(1e-7, 1)
ax.set_xlabel("t")
ax.set_ylabel(r"$|E - E_0| / E_0$")
ax.set_title(f"Relative energy error, HLW rigid body, h = {H_LONG}, {N_LONG:,} steps")
ax.legend(loc="upper left", fontsize=9)
plt.show()

tenth = len(ts) // 10
print(f"{'method':10s} {'max err, first 10%':>19s} {'max err, last 10%':>18s} "
      f"{'|Pi| error':>11s} {'g^T g - I':>10s}")
for name, (_, err, m, g) in long_runs.items():
    cas = np.max(np.abs(np.linalg.norm(m, axis=-1) - np.linalg.norm(m[0])))
    orth = float(jnp.max(diagnostics.orthogonality_defect(body, jnp.asarray(g))))
    print(f"DEP {name:6s} {err[:tenth].max():19.2e} {err[-tenth:].max():18.2e} "
          f"{cas:11.1e} {orth:10.1e}")
    # bounded: no growth from the first to the last tenth of the run
    assert err.max() < 1e-3 and err[-tenth:].max() < 1.5 * err[:tenth].max()
    assert cas < 1e-12 and orth < 1e-12
rk_cas = np.max(np.abs(np.linalg.norm(rk_m, axis=-1) - np.linalg.norm(rk_m[0])))
print(f"{'RK2':10s} {rk_err[:tenth].max():19.2e} {rk_err[-tenth:].max():18.2e} {rk_cas:11.1e}")

# %% [markdown]
# At full size both DEP variants keep the relative energy error at most $8.6\cdot10^{-5}$
# (exp chart) and $2.5\cdot10^{-4}$ (Cayley chart) over the whole run: it oscillates with the rotation and its
# envelope in the last tenth of the run equals that in the first tenth — no drift, as backward
# error analysis predicts for a symplectic (Lie–Poisson) map. The Casimir $|\Pi|$ and the
# orthogonality $g^\top g = I$ hold to round-off. The explicit midpoint rule, of the same
# order, drifts steadily (about 9 % after $10^5$ steps) and does not keep $|\Pi|$ either.

# %% [markdown]
# ## 3. Convergence order — and the paper's open question
#
# The paper (end of §5) recalls that the Lewis–Simo algorithm (5.7), with its increment
# written as $f_{k+1\,k} = \mathrm{cay}(\xi_{k+1\,k})$, is second order, and adds: *"It is not clear, however, whether the
# second-order accuracy can be maintained in the absence of the Cayley transform."*
#
# We measure it. Both charts integrate the HLW problem to $T = 2$ with $h = 0.1/2^k$; the
# error is the max-norm distance of $(\Pi_N, g_N)$ from a DOP853 reference solution at
# tolerance $10^{-13}$ (`lievi.reference_solution`), and the order is the slope of a
# least-squares fit of $\log(\text{error})$ on $\log h$.

# %%
g_ref, m_ref = lievi.reference_solution(body, g0, m0, np.array([0.0, T_CONV]))


def final_error(dep, h):
    n = int(round(T_CONV / h))
    sol = lievi.simulate(body, dep, g0, m0, h=h, n_steps=n, save=lievi.Save(every=n))
    return max(np.max(np.abs(np.asarray(sol.m[-1]) - m_ref[-1])),
               np.max(np.abs(np.asarray(sol.g[-1]) - g_ref[-1])))


hs = np.asarray(HS)
errors = {name: np.array([final_error(dep, h) for h in hs]) for name, dep in CHARTS.items()}
orders = {name: np.polyfit(np.log(hs), np.log(err), 1)[0] for name, err in errors.items()}

print(f"{'h':>10s}" + "".join(f"{'error ' + n:>14s}{'ratio':>7s}" for n in CHARTS))
for i, h in enumerate(hs):
    row = f"{h:10.5f}"
    for name in CHARTS:
        ratio = errors[name][i - 1] / errors[name][i] if i else float("nan")
        row += f"{errors[name][i]:14.3e}{ratio:7.3f}"
    print(row)
for name, p in orders.items():
    print(f"fitted order, {name:6s} chart: {p:.4f}")
    assert abs(p - 2) < 0.05

# %%
fig, ax = plt.subplots(figsize=(6.5, 5))
for name in CHARTS:
    ax.loglog(hs, errors[name], "o-", color=COLORS[name],
              label=f"DEP, {name} chart (fitted order {orders[name]:.3f})")
guide = errors["cayley"][0] * 2 * (hs / hs[0]) ** 2
ax.loglog(hs, guide, "k--", lw=1, label="slope 2")
ax.set_xlabel("h")
ax.set_ylabel(r"max error of $(\Pi, g)$ at $T = 2$")
ax.set_title("Convergence on the HLW rigid body")
ax.legend()
plt.show()

# %% [markdown]
# **Answer to the open question: yes — second order holds for the exponential chart too.**
# The error ratio per halving of $h$ is 4.00 for both charts and the fitted orders are 2 to
# within $3\cdot10^{-3}$ at full size (printed above). On this problem the exponential chart
# is even about 36 times more accurate than the Cayley chart at the same step size.
#
# This is no accident of the test problem. For any chart with $\varphi(-\xi) = \varphi(\xi)^{-1}$
# — true of both $\exp$ and $\mathrm{cay}$ — and any reduced Lagrangian $l$, the discrete
# Lagrangian is *self-adjoint*:
# $L_d(g_{k+1}, g_k; -h) = -h\,l\big(\varphi^{-1}(F_k^{-1})/(-h)\big) = -h\,l\big(\varphi^{-1}(F_k)/h\big) = -L_d(g_k, g_{k+1}; h)$.
# A variational integrator with a self-adjoint discrete Lagrangian is a symmetric method,
# $\Phi_{-h} = \Phi_h^{-1}$ (Marsden & West, *Discrete mechanics and variational
# integrators*, Acta Numerica 2001), and a consistent symmetric method has even order (Hairer, Lubich
# & Wanner, *Geometric Numerical Integration*, Thm. II.3.2), hence order at least 2. The
# last cell checks the symmetry numerically: one step forward with $h$ and one with $-h$
# return to the initial state to round-off.

# %%
for name, dep in CHARTS.items():
    # one step (g, Pi) -> (g', Pi'); h is traced, so +h and -h share one compilation
    step = jax.jit(lambda g, m, h, dep=dep: dep.step(body, g, m, h))
    g1, m1, _ = step(g0, m0, 0.1)
    g_back, m_back, _ = step(g1, m1, -0.1)
    defect = max(float(jnp.max(jnp.abs(g_back - g0))), float(jnp.max(jnp.abs(m_back - m0))))
    print(f"{name:6s} chart: |Phi_(-h)(Phi_h(g0, Pi0)) - (g0, Pi0)| = {defect:.1e}")
    assert defect < 1e-13

# %% [markdown]
# ## Summary
#
# - The DEP/DLP integrator keeps the momentum on its coadjoint orbit (the sphere) to round-off
#   and close to the energy ellipsoid: discrete polhodes look like the exact ones, including the
#   separatrix behaviour near the intermediate axis.
# - Over $10^5$ steps at $h = 0.1$ the energy error is bounded ($8.6\cdot10^{-5}$ for the
#   exponential chart, $2.5\cdot10^{-4}$ for Cayley, relative) with no drift.
# - Both charts are second order; the exponential chart answers the open question of §5 in
#   the affirmative, and the reason is the symmetry of the discrete Lagrangian.
