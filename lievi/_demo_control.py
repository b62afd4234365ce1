"""`python -m lievi demo --problem control`: optimal control through the integrator.

Rest-to-rest reorientation of a rigid body: from rest at `g = I` to rest at
`g_f = exp(θ_f â)` (θ_f = 150° about `a = (1, 2, 2)/3`) in fixed time `T = 2`, minimising
`Σ_k h|u_k|²` over a held control sequence `u` (`lievi.Control`: body torques, one per
step, the discrete Lagrange–d'Alembert forces `(h/2)u_k` at both ends of step `k`).
The terminal conditions `c = (log(g_fᵀ g_N), Π_N) = 0` are imposed by an augmented
Lagrangian, `λ·c + (ρ/2)|c|²`, minimised by `optax.lbfgs` for fixed `λ` with exact
gradients through `lievi.simulate`; then `λ ← λ + ρc` (the method of multipliers), so the
conditions are met to round-off rather than to `O(1/ρ)`.

**Closed form for a spherical body** `J = jI`. Euler's equation is `jΩ̇ = u` (`Π × Ω = 0`),
so `∫|u|² = j²∫|Ω̇|²`: the rest-to-rest problem is the minimum-acceleration (Riemannian
cubic) problem on SO(3) with its bi-invariant metric (Noakes, Heinzinger & Paden, IMA J.
Math. Control Inf. 6 (1989)). About the fixed axis `a`, `min ∫ j²θ̈² dt` with
`θ(0) = θ̇(0) = θ̇(T) = 0`, `θ(T) = θ_f` has the Euler–Lagrange equation `θ'''' = 0`, so

    θ(t) = θ_f (3s² − 2s³),  s = t/T,   u(t) = (j θ_f / T²)(6 − 12s) a,
    J* = ∫|u|² dt = 12 j² θ_f² / T³.

Along the axis the discrete problem is the continuous one with the integrals replaced by
midpoint sums (`θ_N = Σ h u_k (T − t_{k+½})` exactly), whose optimum is again linear in
time; the midpoint rule's error on `∫(t − T/2)²` gives `J_d/J* − 1 = 1/(N² − 1)` for `N`
steps: second order in `h`. The demo starts the sphere from a random control with
components off the axis and checks that the optimum comes out on the eigenaxis. An
asymmetric spacecraft (`I = (1, 2, 3)`) follows: no closed form, the gyroscopic coupling
moves its optimum off the eigenaxis.

The helpers (`lbfgs`, `terminal_defect`, `reorient`, `closed_form_control`) are the
ones the test suite checks; read them as a template for other control problems.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import optax
import optax.tree_utils as otu

import lievi

THETA = 5 * np.pi / 6  # 150°
AXIS = jnp.array([1.0, 2.0, 2.0]) / 3
T = 2.0
PENALTY = 100.0  # ρ of the augmented Lagrangian
GRADIENT_TOLERANCE = 1e-11  # of each inner L-BFGS solve
SPACECRAFT_INERTIA = (1.0, 2.0, 3.0)
DEFAULT_STEPS = 60  # the spacecraft's N
SPHERE_STEPS = (16, 32)
ATTITUDE_TOLERANCE = 1e-6  # rad, at T: the demo's success criterion


def lbfgs(fun, x0, max_iter: int, tol: float):
    """Minimise `fun` from `x0` with `optax.lbfgs` in a `lax.while_loop` (jit-compatible).

    Stops when the gradient norm is below `tol` or after `max_iter` iterations.
    """
    opt = optax.lbfgs(memory_size=20)
    value_and_grad = optax.value_and_grad_from_state(fun)

    def step(carry):
        x, state = carry
        value, grad = value_and_grad(x, state=state)
        updates, state = opt.update(grad, state, x, value=value, grad=grad, value_fn=fun)
        return optax.apply_updates(x, updates), state

    def keep_going(carry):
        _, state = carry
        count, grad = otu.tree_get(state, "count"), otu.tree_get(state, "grad")
        return (count == 0) | ((count < max_iter) & (otu.tree_norm(grad) >= tol))

    x, _ = jax.lax.while_loop(keep_going, step, (x0, opt.init(x0)))
    return x


def terminal_defect(system, integrator, u, h, g_target):
    """`c = (log(g_fᵀ g_N), Π_N)`: zero exactly at rest at the target."""
    n = u.shape[0]
    sol = lievi.simulate(
        system,
        integrator,
        jnp.eye(3),
        jnp.zeros(3),
        h=h,
        n_steps=n,
        save_every=n,
        forcing=lievi.Control(u),
        throw=False,
    )
    return jnp.concatenate([lievi.SO3.log(g_target.T @ sol.g[-1]), sol.m[-1]])


def reorient(
    system,
    g_target,
    n,
    *,
    integrator=lievi.DEP(),
    u0=None,
    max_outer: int = 15,
    tol: float = 1e-12,
):
    """The discrete optimal control `u` (n, 3) over `T`, and the terminal defect it leaves.

    **Arguments:** `system` (a rigid body), `g_target` (3×3), `n` (steps, `h = T/n`),
    `integrator`, `u0` (initial guess; zeros by default), `max_outer` (multiplier updates),
    `tol` (on `max|c|`, ends the outer loop).

    **Returns:** `(u, c, outer)`: the control, the terminal defect `c`, and the number of
    outer (multiplier) iterations taken.
    """
    h = T / n

    @jax.jit
    def inner(u, multiplier):
        def objective(u):
            c = terminal_defect(system, integrator, u, h, g_target)
            return h * jnp.sum(u**2) + multiplier @ c + PENALTY / 2 * c @ c

        u = lbfgs(objective, u, 3000, GRADIENT_TOLERANCE)
        return u, terminal_defect(system, integrator, u, h, g_target)

    u = jnp.zeros((n, 3)) if u0 is None else u0
    multiplier = jnp.zeros(6)
    outer = 0
    for outer in range(1, max_outer + 1):
        u, c = inner(u, multiplier)
        multiplier = multiplier + PENALTY * c
        if float(jnp.max(jnp.abs(c))) < tol:
            break
    return u, c, outer


def closed_form_control(j, n):
    """The spherical body's optimal `u(t)` at the step midpoints, (n, 3)."""
    s = (np.arange(n) + 0.5) / n
    return (j * THETA / T**2 * (6 - 12 * s))[:, None] * np.asarray(AXIS)


def sphere_optimum(n, j=1.0):
    """The spherical body's discrete optimum against the closed form.

    **Returns:** a dict: `cost` (`Σ h|u_k|²`), `optimum` (`J*`), `cost_error`
    (`J_d/J* − 1`), `profile_error` (max |u − u(t_{k+½})| / max|u|), `off_axis`
    (max |component of u off the axis|), `defect` (max |c|), `u`.
    """
    sphere = lievi.RigidBody(jnp.full(3, j))
    g_target = lievi.SO3.exp(THETA * AXIS)
    u0 = jnp.asarray(0.1 * np.random.default_rng(n).normal(size=(n, 3)))  # off the axis
    u, c, _ = reorient(sphere, g_target, n, u0=u0)
    h = T / n
    cost = float(h * jnp.sum(u**2))
    optimum = 12 * j**2 * THETA**2 / T**3
    return {
        "cost": cost,
        "optimum": optimum,
        "cost_error": (cost - optimum) / optimum,
        "profile_error": float(jnp.max(jnp.abs(u - closed_form_control(j, n))))
        / (6 * j * THETA / T**2),
        "off_axis": float(jnp.max(jnp.abs(u - (u @ AXIS)[:, None] * AXIS))),
        "defect": float(jnp.max(jnp.abs(c))),
        "u": u,
    }


def spacecraft_manoeuvre(n, integrator=lievi.DEP()):
    """The asymmetric spacecraft's optimum, re-simulated with `throw=True`.

    **Returns:** a dict: `cost`, `attitude_error` (rad, `|log(g_fᵀ g_N)|`), `final_momentum`
    (max |Π_N|), `off_axis_share` (`|u − (u·a)a| / |u|` over the whole sequence),
    `outer` (multiplier updates), `u`.
    """
    craft = lievi.RigidBody(jnp.array(SPACECRAFT_INERTIA))
    g_target = lievi.SO3.exp(THETA * AXIS)
    u, _, outer = reorient(craft, g_target, n, integrator=integrator)
    sol = lievi.simulate(
        craft, integrator, jnp.eye(3), jnp.zeros(3), h=T / n, n_steps=n, forcing=lievi.Control(u)
    )
    along = (u @ AXIS)[:, None] * AXIS
    return {
        "cost": float(T / n * jnp.sum(u**2)),
        "attitude_error": float(jnp.linalg.norm(lievi.SO3.log(g_target.T @ sol.g[-1]))),
        "final_momentum": float(jnp.max(jnp.abs(sol.m[-1]))),
        "off_axis_share": float(jnp.linalg.norm(u - along) / jnp.linalg.norm(u)),
        "outer": outer,
        "u": u,
    }


def save_plot(path, sphere_n, sphere_u, craft_u) -> None:
    """Left: the sphere's discrete optimum against the closed form; right: the
    spacecraft's torques."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
    for ax, u, title in (
        (left, sphere_u, f"spherical body, N = {sphere_n}: u·a against the closed form"),
        (right, craft_u, f"spacecraft I = {SPACECRAFT_INERTIA}, N = {len(craft_u)}: torques"),
    ):
        n = len(u)
        edges = np.linspace(0, T, n + 1)
        if u is sphere_u:
            t = np.linspace(0, T, 400)
            ax.plot(t, THETA / T**2 * (6 - 12 * t / T), "k", lw=3, alpha=0.3, label="closed form")
            ax.stairs(np.asarray(u @ AXIS), edges, baseline=None, label="discrete optimum u·a")
        else:
            for i in range(3):
                ax.stairs(np.asarray(u[:, i]), edges, baseline=None, label=f"$u_{i + 1}$")
        ax.set_title(title, fontsize="medium")
        ax.set_xlabel("t")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize="small")
    fig.suptitle("lievi: rest-to-rest reorientation by 150°, minimum Σ h|u|²")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main(args: argparse.Namespace) -> int:
    """Run the control demo; 0 when every solve met its terminal conditions and every
    requested output was written, 1 otherwise (outputs are checked by the caller)."""
    from ._demo import _device_description

    if args.h is not None:
        print(
            "lievi demo: error: --h does not apply to --problem control (the time T = 2 is "
            "fixed; choose the number of steps with --steps, h = T/N).",
            file=sys.stderr,
        )
        return 2
    n = int(args.steps) if args.steps is not None else DEFAULT_STEPS
    print(
        "\n".join(
            [
                "lievi demo: optimal control, rest-to-rest reorientation of a rigid body",
                f"  150° about a = (1, 2, 2)/3 in T = {T:g}; minimise Σ h|u_k|² over held body "
                "torques u_k (lievi.Control)",
                "  terminal conditions g_N = exp(θa^), Π_N = 0 by an augmented Lagrangian; "
                "inner solver optax L-BFGS",
                "  with gradients through lievi.simulate (DEP, exp chart); "
                f"device {_device_description()}, float64",
            ]
        ),
        flush=True,
    )
    print(
        "\nspherical body J = I, started off the axis; closed-form optimum "
        f"J* = 12θ²/T³ = {12 * THETA**2 / T**3:.6f} (the eigenaxis manoeuvre)",
        flush=True,
    )
    header = (
        f"{'N':>4}  {'J_d/J* − 1':>11}  {'1/(N²−1)':>10}  {'off-axis':>9}  {'defect':>9}  time [s]"
    )
    print(header + "\n" + "-" * len(header), flush=True)
    ok, sphere_rows = True, []
    for n_sphere in SPHERE_STEPS:
        start = time.perf_counter()
        row = sphere_optimum(n_sphere)
        row["time_s"] = time.perf_counter() - start
        sphere_rows.append(row)
        ok &= row["defect"] < 1e-10
        print(
            f"{n_sphere:>4}  {row['cost_error']:>11.4e}  {1 / (n_sphere**2 - 1):>10.4e}  "
            f"{row['off_axis']:>9.1e}  {row['defect']:>9.1e}  {row['time_s']:8.1f}",
            flush=True,
        )

    print(f"\nasymmetric spacecraft I = {SPACECRAFT_INERTIA}, N = {n} (h = {T / n:g})", flush=True)
    start = time.perf_counter()
    craft = spacecraft_manoeuvre(n)
    craft["time_s"] = time.perf_counter() - start
    ok &= craft["attitude_error"] <= ATTITUDE_TOLERANCE
    print(
        f"  cost Σ h|u|² = {craft['cost']:.6f}\n"
        f"  attitude error at T = {craft['attitude_error']:.2e} rad, max |Π_N| = "
        f"{craft['final_momentum']:.2e}\n"
        f"  share of |u| off the eigenaxis = {craft['off_axis_share']:.3f} "
        "(gyroscopic coupling; 0 for the sphere)\n"
        f"  {craft['outer']} multiplier updates, {craft['time_s']:.1f} s",
        flush=True,
    )
    if not ok:
        print("\nlievi demo: a solve did not meet its terminal conditions.", file=sys.stderr)

    written = True
    if args.json:
        document = {
            "problem": {"theta_deg": 150.0, "axis": [1 / 3, 2 / 3, 2 / 3], "T": T},
            "sphere": [
                {"n_steps": n_s, **{k: v for k, v in r.items() if k != "u"}}
                for n_s, r in zip(SPHERE_STEPS, sphere_rows)
            ],
            "spacecraft": {
                "inertia": list(SPACECRAFT_INERTIA),
                "n_steps": n,
                **{k: v for k, v in craft.items() if k != "u"},
                "u": np.asarray(craft["u"]).tolist(),
            },
            "device": str(jax.devices()[0]),
        }
        try:
            with open(args.json, "w", encoding="utf-8") as f:
                json.dump(document, f, indent=2, ensure_ascii=False)
                f.write("\n")
            print(f"\nresults written to {args.json}")
        except OSError as error:
            written = False
            print(f"lievi demo: error: --json {args.json!r}: {error}", file=sys.stderr)
    if args.plot:
        try:
            save_plot(args.plot, SPHERE_STEPS[-1], sphere_rows[-1]["u"], craft["u"])
            print(f"figure written to {args.plot}")
        except OSError as error:
            written = False
            print(f"lievi demo: error: --plot {args.plot!r}: {error}", file=sys.stderr)
    return 0 if ok and written else 1
