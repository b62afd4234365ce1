"""Work–precision: the cost of reaching a final attitude error, lievi against MuJoCo and diffrax.

Two problems, T = 20, float64, every body the same system with its own initial momentum
(the base momentum times `1 + 0.05·noise` per component):

- **free body**: principal moments `(0.6, 0.8, 1.0)`, `Π₀ = (1.8, 0.4, −0.9)`, `g₀ = 1`;
- **heavy top**: the same moments about the centre of mass (`heavy_top(...,
  inertia_about="center_of_mass")`), mass 1, `ρ = (0, 0, 0.5)` (on a principal axis, so the
  moments about the fixed point are principal moments too and lievi's fast paths apply;
  with `I₁ ≠ I₂` the top is not integrable), gravity 1, `Π₀ = (0.5, 0.3, 1.2)`,
  `g₀ = exp(0.3, −0.2, 0.1)`.

(MuJoCo requires a physical body — its principal moments satisfy the triangle inequality —
so the Hairer–Lubich–Wanner body `(2, 1, 2/3)` of the other benchmarks is not used here.)

For each method and step size (each tolerance, for adaptive diffrax), one batched run is
timed (after compilation, best of two), and the error is the largest over the first
`--reference` bodies of `‖g(T) − g_ref(T)‖_F`, `g_ref` from DOP853 at 1e-13
(`lievi.reference_solution`). The cost is seconds per million bodies for the whole
horizon. Methods:

- lievi: `DEP(exp)`, `MoserVeselov`, `LiePoissonSplitting`, `RKMK4`, `RKMK5`, `RKMK8`
  (the Lie-group Runge–Kutta methods of order 4, 5, 8; the order-8 ones also at h = 0.8, 0.4)
  (structure-of-arrays fast paths, with gravity too), `RK4` (embedded; fast path for the
  free body), `Composition(LiePoissonSplitting, 4 | 6 | 8)` (the fused composition kernel), all through
  `lievi.simulate_batch`;
- diffrax: `Tsit5` and `Dopri8` with constant steps (Dopri8 also at h = 0.8, 0.4), and
  `Dopri8` with a PID controller at tolerances 1e-4 … 1e-12, the state one flat array of 12 numbers (`R` row-major and `Π`), the field
  `Ṙ = R Ω̂`, `Π̇ = Π × Ω + mγ Γ × ρ` (`Γ` the last row of `R`), vmapped over the batch;
- MuJoCo (`mujoco.rollout`, the C engine, on every core): `Euler`, `implicitfast`, `RK4`,
  a free joint (free body, gravity off) or a ball joint at the fixed point (heavy top), the
  MJCF written here. MuJoCo runs its general articulated-body pipeline every step (mass
  matrix, bias forces, collision detection with nothing to collide, constraint solver
  with no constraints), which lievi's closed-form steps do not: this is the comparison a
  user choosing a tool makes, not one of equal arithmetic. Timed on `--mujoco-batch`
  bodies (its cost per body does not depend on the batch).

The table printed (and written to `benchmarks/results/work_precision.json`, with a PNG of
error against cost per problem) also gives, for every target error 1e-2 … 1e-10, the
cheapest run of each family that reaches it, and how many times cheaper lievi's is than
the cheaper of the other two (`lievi_advantage`).

**Invariants over a long run** (`long_run` in the JSON): every method again, on the first
`--reference` bodies, for `LONG_STEPS = 10⁵` steps of `LONG_H = 0.05` (T = 5000; diffrax's
Dopri8 over the same horizon at tolerance `LONG_TOL = 1e-8`): the largest relative energy
error `|H(T) − H(0)|/|H(0)|`, the largest momentum error `|J(T) − J(0)|/|Π₀|` (`J` the
spatial angular momentum `gΠ` of the free body, the vertical one `e₃·gΠ` of the heavy top:
the Noether momenta of the symmetries each problem has) and, for the methods that carry
the attitude as a matrix (lievi's and diffrax's), `‖gᵀg − I‖_F` at the end (MuJoCo
carries a quaternion, normalised every step). All from `lievi.diagnostics` on the final
states.

    python benchmarks/work_precision.py [--batch 4096] [--quick] [--no-long-run]

`mujoco` and `diffrax` are optional (`pip install -e .[bench]` brings both); a family whose
package is missing is skipped and said so.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np

jax.config.update("jax_enable_x64", True)

import lievi  # noqa: E402

T = 20.0
MOMENTS = np.array([0.6, 0.8, 1.0])
MASS, GRAVITY = 1.0, 1.0
RHO = np.array([0.0, 0.0, 0.5])
PROBLEMS = {
    "free body": dict(m0=np.array([1.8, 0.4, -0.9]), tilt=np.zeros(3), gravity=False),
    "heavy top": dict(m0=np.array([0.5, 0.3, 1.2]), tilt=np.array([0.3, -0.2, 0.1]), gravity=True),
}
TARGETS = [10.0**-k for k in range(2, 11)]
LONG_STEPS, LONG_H, LONG_TOL = 100_000, 0.05, 1e-8


def lievi_system(problem):
    if PROBLEMS[problem]["gravity"]:
        return lievi.heavy_top(
            jnp.asarray(MOMENTS), MASS, jnp.asarray(RHO), GRAVITY, inertia_about="center_of_mass"
        )
    return lievi.RigidBody(jnp.asarray(MOMENTS))


def moments_about_the_fixed_point(problem):
    """The principal moments the equations use (for the heavy top, shifted from the centre
    of mass to the fixed point)."""
    return np.asarray(lievi_system(problem).inertia)


def initial_states(problem, batch, seed=0):
    spec = PROBLEMS[problem]
    rng = np.random.default_rng(seed)
    m0 = spec["m0"] * (1 + 0.05 * rng.normal(size=(batch, 3)))
    g0 = np.asarray(lievi.SO3.exp(jnp.asarray(spec["tilt"])))
    return g0, m0


def reference(problem, count):
    system = lievi_system(problem)
    g0, m0 = initial_states(problem, count)
    finals = []
    for k in range(count):
        g_ref, _ = lievi.reference_solution(system, jnp.asarray(g0), jnp.asarray(m0[k]), [0.0, T])
        finals.append(np.asarray(g_ref[-1]))
    return np.array(finals)


def attitude_error(g_final, g_ref):
    count = g_ref.shape[0]
    return float(np.max(np.linalg.norm(np.asarray(g_final[:count]) - g_ref, axis=(-2, -1))))


def timed(fn, *args):
    """`(result, seconds)`: compiled and run once, then the best of two runs."""
    out = jax.block_until_ready(fn(*args))
    best = np.inf
    for _ in range(2):
        start = time.perf_counter()
        out = jax.block_until_ready(fn(*args))
        best = min(best, time.perf_counter() - start)
    return out, best


# ---- lievi --------------------------------------------------------------------------------


LIEVI_METHODS = {
    "lievi DEP exp": (lambda: lievi.DEP(), 2),
    "lievi Moser-Veselov": (lambda: lievi.MoserVeselov(), 2),
    "lievi splitting": (lambda: lievi.LiePoissonSplitting(), 2),
    "lievi RK4 (embedded)": (lambda: lievi.RK4(), 4),
    "lievi RKMK4": (lambda: lievi.RKMK4(), 4),
    "lievi RKMK5": (lambda: lievi.RKMK5(), 5),
    "lievi RKMK8": (lambda: lievi.RKMK8(), 8),
    "lievi splitting ∘ 4": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=4), 4),
    "lievi splitting ∘ 6": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=6), 6),
    "lievi splitting ∘ 8": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=8), 8),
}


def lievi_run(problem, method, h, batch, n=None, with_m=False):
    """`(g(T), seconds, ok)`, or `(g, m, seconds, ok)` after `n` steps with `with_m`."""
    system = lievi_system(problem)
    g0, m0 = initial_states(problem, batch)
    n = int(round(T / h)) if n is None else n
    integrator = LIEVI_METHODS[method][0]()
    save = lievi.Save(g=True, m=with_m, stats=False)

    @jax.jit
    def run(m0):
        sol = lievi.simulate_batch(
            system, integrator, jnp.asarray(g0), m0, h=h, n_steps=n, save=save, throw=False
        )
        return sol.g[:, -1], (sol.m[:, -1] if with_m else None), sol.result

    (g_final, m_final, result), seconds = timed(run, jnp.asarray(m0))
    ok = bool(np.all(np.asarray(result) == 0))
    if with_m:
        return np.asarray(g_final), np.asarray(m_final), seconds, ok
    return np.asarray(g_final), seconds, ok


# ---- diffrax ------------------------------------------------------------------------------


def diffrax_field(problem):
    gravity = PROBLEMS[problem]["gravity"]
    inverse = jnp.asarray(1 / moments_about_the_fixed_point(problem))
    rho = jnp.asarray(MASS * GRAVITY * RHO)

    def field(t, y, args):
        R, P = y[:9].reshape(3, 3), y[9:]
        w = P * inverse
        W = jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])
        P_dot = jnp.cross(P, w)
        if gravity:
            P_dot = P_dot + jnp.cross(R[2], rho)
        return jnp.concatenate([(R @ W).reshape(9), P_dot])

    return field


def diffrax_run(problem, solver_name, h_or_tol, batch, t1=T, with_m=False):
    """`(g(t1), seconds, ok)`, or `(g, Π, seconds, ok)` with `with_m`."""
    import diffrax

    g0, m0 = initial_states(problem, batch)
    y0 = np.concatenate([np.broadcast_to(g0.reshape(9), (batch, 9)), m0], axis=1)
    term = diffrax.ODETerm(diffrax_field(problem))
    if solver_name in ("Tsit5", "Dopri8 constant"):
        # Constant steps: no error estimate, no rejected steps (the cheapest way to run a
        # fixed tableau in diffrax, and the like-for-like baseline of lievi's RKMK methods).
        n = int(round(t1 / h_or_tol))
        kwargs = dict(
            solver=diffrax.Tsit5() if solver_name == "Tsit5" else diffrax.Dopri8(),
            dt0=h_or_tol,
            stepsize_controller=diffrax.ConstantStepSize(),
            max_steps=n,
        )
    else:
        kwargs = dict(
            solver=diffrax.Dopri8(),
            dt0=None,
            stepsize_controller=diffrax.PIDController(rtol=h_or_tol, atol=h_or_tol),
            max_steps=100 * LONG_STEPS,
        )

    @jax.jit
    def run(y0):
        def one(y):
            sol = diffrax.diffeqsolve(
                term, t0=0.0, t1=t1, y0=y, saveat=diffrax.SaveAt(t1=True), throw=False, **kwargs
            )
            return sol.ys[-1], sol.result == diffrax.RESULTS.successful

        return jax.vmap(one)(y0)

    (y, ok), seconds = timed(run, jnp.asarray(y0))
    g, ok = np.asarray(y[:, :9]).reshape(-1, 3, 3), bool(np.all(np.asarray(ok)))
    return (g, np.asarray(y[:, 9:]), seconds, ok) if with_m else (g, seconds, ok)


# ---- MuJoCo -------------------------------------------------------------------------------


def mjcf(problem, h, integrator):
    if PROBLEMS[problem]["gravity"]:
        joint, gravity, pos = '<joint type="ball"/>', f"0 0 -{GRAVITY}", " ".join(map(str, RHO))
    else:
        joint, gravity, pos = "<freejoint/>", "0 0 0", "0 0 0"
    inertia = " ".join(map(str, MOMENTS))
    return f"""
<mujoco>
  <option timestep="{h}" integrator="{integrator}" gravity="{gravity}"/>
  <worldbody>
    <body name="body">
      {joint}
      <inertial pos="{pos}" mass="{MASS}" diaginertia="{inertia}"/>
    </body>
  </worldbody>
</mujoco>"""


def mujoco_run(problem, integrator, h, batch, chunk=200, n=None, with_m=False):
    """`(g(T), seconds, ok)`, or `(g, Π, seconds, ok)` after `n` steps with `with_m`."""
    import mujoco
    from mujoco import rollout

    model = mujoco.MjModel.from_xml_string(mjcf(problem, h, integrator))
    threads = os.cpu_count() or 1
    datas = [mujoco.MjData(model) for _ in range(threads)]
    g0, m0 = initial_states(problem, batch)
    data = datas[0]
    q0 = np.asarray(lievi.matrix_to_quaternion_wxyz(jnp.asarray(g0)))
    free = not PROBLEMS[problem]["gravity"]
    # Angular velocity in the body frame (MuJoCo's free and ball joints use the local frame).
    omega = m0 / moments_about_the_fixed_point(problem)
    spec = mujoco.mjtState.mjSTATE_FULLPHYSICS
    states = []
    for k in range(batch):
        mujoco.mj_resetData(model, data)
        if free:
            data.qpos[3:7] = q0
            data.qvel[3:6] = omega[k]
        else:
            data.qpos[:4] = q0
            data.qvel[:3] = omega[k]
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)
        states.append(state)
    initial = np.array(states)
    n = int(round(T / h)) if n is None else n
    start = time.perf_counter()
    state = initial
    done = 0
    while done < n:
        steps = min(chunk, n - done)
        out, _ = rollout.rollout(model, datas, state, nstep=steps)
        state = out[:, -1, :]
        done += steps
    seconds = time.perf_counter() - start
    # FULLPHYSICS state: time, qpos, qvel, …
    quaternion = state[:, 1 + 3 : 1 + 7] if free else state[:, 1 : 1 + 4]
    g = np.asarray(lievi.quaternion_wxyz_to_matrix(jnp.asarray(quaternion)))
    ok = bool(np.all(np.isfinite(state)))
    if not with_m:
        return g, seconds, ok
    # FULLPHYSICS: time, qpos (7 | 4), qvel (6 | 3); the body angular velocity, times the
    # moments about the joint, is the body momentum Π.
    nq = 7 if free else 4
    omega = state[:, 1 + nq + 3 : 1 + nq + 6] if free else state[:, 1 + nq : 1 + nq + 3]
    return g, omega * moments_about_the_fixed_point(problem), seconds, ok


# ---- the sweep ----------------------------------------------------------------------------


def sweep(problem, batch, mujoco_batch, quick, g_ref):
    steps = [0.2, 0.1, 0.05, 0.025, 0.0125] if not quick else [0.1, 0.05]
    rows = []

    def record(family, method, knob, g_final, seconds, ok, bodies):
        error = attitude_error(g_final, g_ref) if ok else float("nan")
        cost = seconds / bodies * 1e6
        rows.append(dict(family=family, method=method, knob=knob, error=error, cost=cost, ok=ok))
        print(f"  {method:<28} {knob:>9.3g}  error {error:9.2e}  {cost:9.3g} s per 1e6 bodies")

    for method, (_, order) in LIEVI_METHODS.items():
        # The high-order methods reach tight errors at larger steps: start them at 0.8.
        for h in ([0.8, 0.4] if order >= 6 and not quick else []) + steps:
            g_final, seconds, ok = lievi_run(problem, method, h, batch)
            record("lievi", method, h, g_final, seconds, ok, batch)
    try:
        import diffrax  # noqa: F401

        for h in steps:
            record("diffrax", "diffrax Tsit5", h, *diffrax_run(problem, "Tsit5", h, batch), batch)
        for h in [0.8, 0.4] + steps[:3] if not quick else steps:
            record(
                "diffrax", "diffrax Dopri8 (constant step)", h,
                *diffrax_run(problem, "Dopri8 constant", h, batch), batch,
            )  # fmt: skip
        tolerances = [1e-4, 1e-6, 1e-8, 1e-10, 1e-12] if not quick else [1e-6]
        for tol in tolerances:
            record(
                "diffrax", "diffrax Dopri8 (adaptive)", tol,
                *diffrax_run(problem, "Dopri8", tol, batch), batch,
            )  # fmt: skip
    except ImportError:
        print("  diffrax not installed: skipped")
    try:
        import mujoco  # noqa: F401

        for integrator in ("Euler", "implicitfast", "RK4"):
            for h in [x / 4 for x in steps]:
                g_final, seconds, ok = mujoco_run(problem, integrator, h, mujoco_batch)
                record("MuJoCo", f"MuJoCo {integrator}", h, g_final, seconds, ok, mujoco_batch)
    except ImportError:
        print("  mujoco not installed: skipped")
    return rows


def invariant_errors(problem, g0, m0, g, m):
    """`(energy error, momentum error, ‖gᵀg − I‖_F)`, each the largest over the bodies."""
    system = lievi_system(problem)
    g0 = np.broadcast_to(g0, g.shape)

    def invariants(g, m):
        g, m = jnp.asarray(g), jnp.asarray(m)
        J = lievi.diagnostics.spatial_momentum(system, g, m)
        J = J[:, 2:] if PROBLEMS[problem]["gravity"] else J  # vertical / all of it
        return np.asarray(lievi.diagnostics.energy(system, m, g)), np.asarray(J)

    (H0, J0), (H, J) = invariants(g0, m0), invariants(g, m)
    energy = np.max(np.abs(H - H0) / np.abs(H0))
    momentum = np.max(np.linalg.norm(J - J0, axis=-1) / np.linalg.norm(m0, axis=-1))
    defect = np.linalg.norm(np.swapaxes(g, -1, -2) @ g - np.eye(3), axis=(-2, -1)).max()
    return float(energy), float(momentum), float(defect)


def peer_long_runs(problem, count, t1):
    """`(method, knob, run)` of diffrax's and MuJoCo's long runs, where installed."""
    runs = []
    try:
        import diffrax  # noqa: F401

        runs += [
            ("diffrax Tsit5", LONG_H, lambda: diffrax_run(problem, "Tsit5", LONG_H, count, t1, True)),
            ("diffrax Dopri8 (adaptive)", LONG_TOL,
             lambda: diffrax_run(problem, "Dopri8", LONG_TOL, count, t1, True)),
        ]  # fmt: skip
    except ImportError:
        pass
    try:
        import mujoco  # noqa: F401

        runs += [(f"MuJoCo {i}", LONG_H, lambda i=i: mujoco_run(
                  problem, i, LONG_H, count, 1000, LONG_STEPS, True))
                 for i in ("Euler", "implicitfast", "RK4")]  # fmt: skip
    except ImportError:
        pass
    return runs


def long_run(problem, count, methods=None):
    """The invariants after `LONG_STEPS` steps of `LONG_H`, `count` bodies: every method,
    or only the lievi `methods` named."""
    g0, m0 = initial_states(problem, count)
    runs = [(m, LONG_H, lambda m=m: lievi_run(problem, m, LONG_H, count, LONG_STEPS, True))
            for m in (methods or LIEVI_METHODS)]  # fmt: skip
    t1 = LONG_STEPS * LONG_H
    runs += [] if methods else peer_long_runs(problem, count, t1)
    rows = []
    for method, knob, run in runs:
        g, m, seconds, ok = run()
        energy, momentum, defect = invariant_errors(problem, g0, m0, g, m)
        if method.startswith("MuJoCo"):
            defect = None  # a quaternion, normalised every step: no matrix to leave SO(3)
        rows.append(dict(method=method, knob=knob, steps=LONG_STEPS, ok=ok, energy_error=energy,
                         momentum_error=momentum, orthogonality=defect))  # fmt: skip
        print(f"  {method:<28} {knob:>7.3g}  energy {energy:9.2e}  momentum {momentum:9.2e}"
              f"  ‖gᵀg − I‖ {defect if defect is not None else float('nan'):9.2e}")  # fmt: skip
    return rows


def cheapest(rows):
    """Per target error and family, the cheapest run that reaches it."""
    table = {}
    for target in TARGETS:
        entry = {}
        for family in ("lievi", "diffrax", "MuJoCo"):
            hits = [r for r in rows if r["family"] == family and r["ok"] and r["error"] <= target]
            if hits:
                best = min(hits, key=lambda r: r["cost"])
                entry[family] = {k: best[k] for k in ("method", "knob", "cost", "error")}
        others = [entry[f]["cost"] for f in ("diffrax", "MuJoCo") if f in entry]
        if "lievi" in entry and others:
            entry["lievi_advantage"] = min(others) / entry["lievi"]["cost"]
        table[f"{target:.0e}"] = entry
    return table


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 4.5), squeeze=False)
    for ax, (problem, data) in zip(axes[0], results.items()):
        methods = sorted({r["method"] for r in data["rows"]})
        for method in methods:
            rows = [r for r in data["rows"] if r["method"] == method and np.isfinite(r["error"])]
            if not rows:
                continue
            style = "-o" if method.startswith("lievi") else ("--s" if "diffrax" in method else ":^")
            ax.loglog(
                [r["cost"] for r in rows], [r["error"] for r in rows], style, label=method, ms=4
            )
        ax.set_xlabel("seconds per million bodies (T = 20)")
        ax.set_ylabel("final attitude error ‖g − g_ref‖_F")
        ax.set_title(problem)
        ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(fontsize=7, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=120)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=4096)
    parser.add_argument("--mujoco-batch", type=int, default=512)
    parser.add_argument("--reference", type=int, default=8, help="bodies checked against DOP853")
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=list(PROBLEMS))
    parser.add_argument("--quick", action="store_true", help="two step sizes, small batches")
    parser.add_argument("--no-long-run", action="store_true", help="skip the 1e5-step run")
    parser.add_argument(
        "--long-run-only", nargs="+", metavar="METHOD", choices=list(LIEVI_METHODS),
        help="only the invariants after 1e5 steps, of these lievi methods",
    )  # fmt: skip
    parser.add_argument("--out", default="work_precision")
    parser.add_argument("--outdir", default=str(pathlib.Path(__file__).parent / "results"))
    args = parser.parse_args()
    if args.quick:
        args.batch, args.mujoco_batch = min(args.batch, 256), min(args.mujoco_batch, 64)
    load, start = os.getloadavg()[0], time.perf_counter()
    results = {}
    for problem in args.problems:
        print(f"{problem} (T = {T}, batch {args.batch}, MuJoCo batch {args.mujoco_batch}):")
        if args.long_run_only:
            results[problem] = {"long_run": long_run(problem, args.reference, args.long_run_only)}
            continue
        g_ref = reference(problem, args.reference)
        rows = sweep(problem, args.batch, args.mujoco_batch, args.quick, g_ref)
        results[problem] = {"rows": rows, "cheapest": cheapest(rows)}
        if not args.no_long_run:
            print(f"  invariants after {LONG_STEPS} steps of {LONG_H} ({args.reference} bodies):")
            results[problem]["long_run"] = long_run(problem, args.reference)
        print(f"  {'target':>8}  cheapest lievi / diffrax / MuJoCo [s per 1e6 bodies]")
        for target, entry in results[problem]["cheapest"].items():
            cells = [
                f"{entry[f]['cost']:.3g} ({entry[f]['method']}, {entry[f]['knob']:g})"
                if f in entry
                else "—"
                for f in ("lievi", "diffrax", "MuJoCo")
            ]
            advantage = entry.get("lievi_advantage", float("nan"))
            print(f"  {target:>8}  " + " / ".join(cells) + f"  lievi {advantage:.2g}× cheaper")
    outdir = pathlib.Path(args.outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    meta = {
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "load_average_at_start": load,
        "T": T,
        "batch": args.batch,
        "mujoco_batch": args.mujoco_batch,
        "long_run": None if args.no_long_run else dict(steps=LONG_STEPS, h=LONG_H, tol=LONG_TOL),
        "load_average_at_end": os.getloadavg()[0],
        "wall_seconds": time.perf_counter() - start,
    }
    (outdir / f"{args.out}.json").write_text(json.dumps({"meta": meta, **results}, indent=1))
    if not args.long_run_only:
        plot(results, outdir / f"{args.out}.png")
    png = "" if args.long_run_only else " and .png"
    print(f"wrote {outdir / (args.out + '.json')}{png} (load average at start {load:.1f})")


if __name__ == "__main__":
    main()
