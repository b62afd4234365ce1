"""`python -m lievi demo --problem control`: optimal control through the integrator.

Rest-to-rest reorientation of a rigid body: from rest at `g = I` to rest at
`g_f = exp(θ_f â)` (θ_f = 150° about `a = (1, 2, 2)/3`) in fixed time `T = 2`, minimising
`Σ_k h|u_k|²` over a held control sequence `u` (`lievi.Control`: body torques, one per
step), solved by `lievi.solve_optimal_control` (an augmented Lagrangian on the terminal
conditions, `optax.lbfgs`, exact gradients through `lievi.simulate`).

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
"""

from __future__ import annotations

import argparse
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np

import lievi

from .plots import save_control_plot
from .problems import (
    CONTROL_AXIS,
    CONTROL_DEFAULT_STEPS,
    CONTROL_T,
    CONTROL_THETA,
    SPACECRAFT_INERTIA,
    SPHERE_STEPS,
    closed_form_control,
    closed_form_cost,
    control_target,
)
from .report import device_description

ATTITUDE_TOLERANCE = 1e-6  # rad, at T: the demo's success criterion
SPHERE_DEFECT_TOLERANCE = 1e-10


def reorient(system, n, *, integrator=lievi.DEP(), u0=None):
    """`lievi.solve_optimal_control` on the rest-to-rest problem with `n` steps."""
    return lievi.solve_optimal_control(
        system,
        integrator,
        jnp.eye(3),
        jnp.zeros(3),
        control_target(),
        n,
        CONTROL_T / n,
        u0=u0,
    )


def sphere_optimum(n, j=1.0):
    """The spherical body's discrete optimum against the closed form.

    **Returns:** a dict: `cost` (`Σ h|u_k|²`), `optimum` (`J*`), `cost_error`
    (`J_d/J* − 1`), `profile_error` (max |u − u(t_{k+½})| / max|u|), `off_axis`
    (max |component of u off the axis|), `defect` (max |c|), `outer` (multiplier
    updates), `u`.
    """
    sphere = lievi.RigidBody(jnp.full(3, j))
    u0 = jnp.asarray(0.1 * np.random.default_rng(n).normal(size=(n, 3)))  # off the axis
    result = reorient(sphere, n, u0=u0)
    u = result.controls
    optimum = closed_form_cost(j)
    return {
        "cost": result.cost,
        "optimum": optimum,
        "cost_error": (result.cost - optimum) / optimum,
        "profile_error": float(jnp.max(jnp.abs(u - closed_form_control(j, n))))
        / (6 * j * CONTROL_THETA / CONTROL_T**2),
        "off_axis": float(jnp.max(jnp.abs(u - (u @ CONTROL_AXIS)[:, None] * CONTROL_AXIS))),
        "defect": result.constraint_violation,
        "outer": result.iterations,
        "u": u,
    }


def spacecraft_manoeuvre(n, integrator=lievi.DEP()):
    """The asymmetric spacecraft's optimum, re-simulated with `throw=True`.

    **Returns:** a dict: `cost`, `attitude_error` (rad, `|log(g_fᵀ g_N)|`), `final_momentum`
    (max |Π_N|), `off_axis_share` (`|u − (u·a)a| / |u|` over the whole sequence),
    `outer` (multiplier updates), `u`.
    """
    craft = lievi.RigidBody(jnp.array(SPACECRAFT_INERTIA))
    g_target, _ = control_target()
    result = reorient(craft, n, integrator=integrator)
    u = result.controls
    sol = lievi.simulate(
        craft,
        integrator,
        jnp.eye(3),
        jnp.zeros(3),
        h=CONTROL_T / n,
        n_steps=n,
        forcing=lievi.Control(u),
    )
    along = (u @ CONTROL_AXIS)[:, None] * CONTROL_AXIS
    return {
        "cost": result.cost,
        "attitude_error": float(jnp.linalg.norm(lievi.SO3.log(g_target.T @ sol.g[-1]))),
        "final_momentum": float(jnp.max(jnp.abs(sol.m[-1]))),
        "off_axis_share": float(jnp.linalg.norm(u - along) / jnp.linalg.norm(u)),
        "outer": result.iterations,
        "u": u,
    }


def _write_json(path, n, sphere_rows, craft) -> None:
    document = {
        "problem": {"theta_deg": 150.0, "axis": [1 / 3, 2 / 3, 2 / 3], "T": CONTROL_T},
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
    with open(path, "w", encoding="utf-8") as f:
        json.dump(document, f, indent=2, ensure_ascii=False)
        f.write("\n")


def main(args: argparse.Namespace) -> int:
    """Run the control demo (options checked by `check_arguments`); 0 when every solve met
    its terminal conditions and every requested output was written, 1 otherwise."""
    n = int(args.steps) if args.steps is not None else CONTROL_DEFAULT_STEPS
    print(
        "\n".join(
            [
                "lievi demo: optimal control, rest-to-rest reorientation of a rigid body",
                f"  150° about a = (1, 2, 2)/3 in T = {CONTROL_T:g}; minimise Σ h|u_k|² over "
                "held body torques u_k (lievi.Control)",
                "  lievi.solve_optimal_control: terminal conditions g_N = exp(θa^), Π_N = 0 by "
                "an augmented Lagrangian,",
                "  inner solver optax L-BFGS with gradients through lievi.simulate (DEP, exp "
                f"chart); device {device_description()}, float64",
            ]
        ),
        flush=True,
    )
    print(
        "\nspherical body J = I, started off the axis; closed-form optimum "
        f"J* = 12θ²/T³ = {closed_form_cost(1.0):.6f} (the eigenaxis manoeuvre)",
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
        ok &= row["defect"] < SPHERE_DEFECT_TOLERANCE
        print(
            f"{n_sphere:>4}  {row['cost_error']:>11.4e}  {1 / (n_sphere**2 - 1):>10.4e}  "
            f"{row['off_axis']:>9.1e}  {row['defect']:>9.1e}  {row['time_s']:8.1f}",
            flush=True,
        )

    print(
        f"\nasymmetric spacecraft I = {SPACECRAFT_INERTIA}, N = {n} (h = {CONTROL_T / n:g})",
        flush=True,
    )
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
        try:
            _write_json(args.json, n, sphere_rows, craft)
            print(f"\nresults written to {args.json}")
        except OSError as error:
            written = False
            print(f"lievi demo: error: --json {args.json!r}: {error}", file=sys.stderr)
    if args.plot:
        try:
            save_control_plot(args.plot, SPHERE_STEPS[-1], sphere_rows[-1]["u"], craft["u"])
            print(f"figure written to {args.plot}")
        except OSError as error:
            written = False
            print(f"lievi demo: error: --plot {args.plot!r}: {error}", file=sys.stderr)
    return 0 if ok and written else 1
