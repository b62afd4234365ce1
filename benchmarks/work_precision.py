"""Work–precision at two horizons: lievi against diffrax (batch in the state) and MuJoCo.

What a run costs, in CPU seconds per million bodies, to reach a target error, for every
method and step size (every tolerance, for adaptive diffrax). float64; one core each (the
process is pinned to one CPU and XLA to one thread; MuJoCo's `rollout` gets one thread);
each run compiled ahead, then the best of `--repeats` timed calls (process CPU time, so a
loaded machine inflates the figures less than wall time would). Every body is the same
system with its own initial momentum (the base momentum times `1 + 0.05·noise`).

Problems (`PROBLEMS`):

- **free body**: principal moments `(0.6, 0.8, 1.0)`, `Π₀ = (1.8, 0.4, −0.9)`; integrable.
- **HLW body**: the Hairer–Lubich–Wanner body `(2, 1, 2/3)`, `Π₀ = (cos 1.1, 0, sin 1.1)`;
  integrable; not a physical body (the moments break the triangle inequality), so no MuJoCo.
- **heavy top**: moments `(0.6, 0.8, 1.0)` about the centre of mass, mass 1, `ρ = (0, 0,
  0.5)`, gravity 1, `Π₀ = (0.5, 0.3, 1.2)`, `g₀ = exp(0.3, −0.2, 0.1)`; chaotic.
- **Lagrange top**: the same with moments `(0.8, 0.8, 1.0)` (symmetric) and `Π₀ = (0.3,
  −0.2, 2.0)`; integrable.

Errors, each the largest over the first `--reference` bodies and over `SAMPLES` times
evenly spaced in the run, against `lievi.reference_solution` (DOP853, rtol = atol =
1e-13): the rotation angle between `g` and `g_ref` (`attitude`), the distance between
the symmetry axes `g e₃` (`axis`), the relative energy error, and the error of the Noether
momentum (all of `gΠ` for the free bodies, its vertical part for the tops) over `|Π₀|`.
Which of them a run must bring below the target (`TARGETS_SHORT` at T = 20,
`TARGETS_LONG` at T = `--long-T`, default 2·10⁴): the attitude at T = 20; at the long
horizon, trajectory and energy on the integrable problems, energy and momentum on the
chaotic heavy top (two near-exact runs of it part by O(1) rad in attitude by t ≈ 8000:
no method can meet an attitude target there).

Methods: lievi's (`LIEVI_METHODS`, each marked structure-preserving or not: a
structure-preserving one keeps the momentum map to round-off and the energy bounded);
diffrax `Tsit5`, `Dopri5`, `Dopri8` with constant steps and with a PID controller at
rtol = atol = tol, the whole batch as ONE `(12, B)` state (rows Π₁ Π₂ Π₃ g₁₁ … g₃₃, the
field on slices of the one array, `ForwardMode`, `throw=False`) — the fastest
formulation we timed, called "strong"; MuJoCo's C `rollout` (`Euler`,
`implicitfast`, `RK4`; a free joint or a ball joint at the fixed point). The same run
also times an **independent** batch-in-state diffrax runner (`independent_runner`: a
pytree `(Π (3, B), g (3, 3, B))`, another field, diffrax's defaults) and checks that the
strong baseline costs at most 1.1× it (`baseline_check` in the JSON).

The summary per problem and horizon gives, for each target, the cheapest run of each
family, the cheapest structure-preserving lievi run, and the ratios of the strongest
diffrax's cost to each lievi one. Results: `benchmarks/results/<out>.json` and `.png`
(error against cost, one panel per problem and horizon).

    python benchmarks/work_precision.py                     # the published figures (hours)
    python benchmarks/work_precision.py --quick             # a smoke run (minutes)
    python benchmarks/work_precision.py --problems "free body" --horizons short
    python benchmarks/work_precision.py --free-flow         # the heavy top's free flow (~15 min)
    python benchmarks/work_precision.py --coupled binary water   # coupled bodies (hours)

`--coupled`: the binary asteroid and 64 rigid water molecules at a long horizon, targets on
the invariants only, against diffrax on the Newton–Euler equations of all bodies in one
state (`work_precision_coupled.py`).

`--free-flow` asks whether a more accurate free rotation inside the heavy top's splitting
would pay: T = 20, attitude error at equal steps of kick – free flow – kick with today's
free flow (the three-axis splitting) and with the free flow to round-off, alone and in
`Composition(…, 4 | 6 | 8)`; a kick – DMV – kick stage's cost against a splitting stage's
(interleaved rounds); the preprocessed Moser–Veselov step's modified moments per body;
the cost to 1e-4, 1e-6, 1e-8 against diffrax `Dopri8` (batch in the state) in the same
run (`results/work_precision_free_flow.json`).

`mujoco` and `diffrax` are optional (`pip install -e .[bench]`); a missing family is
skipped and said so.
"""

from __future__ import annotations

import argparse
import json
import os
import pathlib
import platform
import sys
import time
from functools import partial

if "--all-cores" not in sys.argv:
    # One core: pin the process (threads inherit it) and keep XLA to one thread.
    os.sched_setaffinity(0, {min(os.sched_getaffinity(0))})
    os.environ["XLA_FLAGS"] = (
        os.environ.get("XLA_FLAGS", "")
        + " --xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"
    )

import jax  # noqa: E402
import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

jax.config.update("jax_enable_x64", True)

import lievi  # noqa: E402

T_SHORT = 20.0
SAMPLES = 25  # every run's step count is a multiple: T/h = 25·2^k
MASS, GRAVITY, RHO = 1.0, 1.0, np.array([0.0, 0.0, 0.5])
PROBLEMS = {
    "free body": dict(
        moments=(0.6, 0.8, 1.0), m0=(1.8, 0.4, -0.9), tilt=(0, 0, 0), gravity=False,
        long_targets=("attitude", "energy"),
    ),
    "HLW body": dict(
        moments=(2.0, 1.0, 2 / 3), m0=(np.cos(1.1), 0.0, np.sin(1.1)), tilt=(0, 0, 0),
        gravity=False, long_targets=("attitude", "energy"), mujoco=False,
    ),
    "heavy top": dict(
        moments=(0.6, 0.8, 1.0), m0=(0.5, 0.3, 1.2), tilt=(0.3, -0.2, 0.1), gravity=True,
        long_targets=("energy", "momentum"),
    ),
    "Lagrange top": dict(
        moments=(0.8, 0.8, 1.0), m0=(0.3, -0.2, 2.0), tilt=(0.3, -0.2, 0.1), gravity=True,
        long_targets=("attitude", "axis", "energy"),
    ),
}  # fmt: skip
TARGETS_SHORT = [10.0**-k for k in range(2, 11)]
TARGETS_LONG = [10.0**-k for k in range(2, 9)]
QUANTITIES = ("attitude", "axis", "energy", "momentum")


def any_problem(spec):
    return True


def free_bodies(spec):
    return not spec["gravity"]


def symmetric_tops(spec):
    """A top whose first two moments are equal: `SymmetricTopSplitting`'s problems."""
    return spec["gravity"] and spec["moments"][0] == spec["moments"][1]


# name: (integrator, order, structure-preserving, the problems it runs on)
LIEVI_METHODS = {
    "DEP exp": (lambda: lievi.DEP(), 2, True, any_problem),
    "Moser-Veselov": (lambda: lievi.MoserVeselov(), 2, True, any_problem),
    "splitting": (lambda: lievi.LiePoissonSplitting(), 2, True, any_problem),
    "splitting ∘ 4": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=4), 4, True, any_problem),
    "splitting ∘ 6": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=6), 6, True, any_problem),
    "splitting ∘ 8": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=8), 8, True, any_problem),
    "splitting ∘ 6 SS": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), 6, "sofroniou-spaletta"), 6, True, any_problem),
    "splitting ∘ 8 SS": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), 8, "sofroniou-spaletta"), 8, True, any_problem),
    "preprocessed MV(6)": (lambda: lievi.PreprocessedMoserVeselov(6), 6, True, free_bodies),
    "preprocessed MV(8)": (lambda: lievi.PreprocessedMoserVeselov(8), 8, True, free_bodies),
    "symmetric top RKN 4": (lambda: lievi.SymmetricTopSplitting(4), 4, True, symmetric_tops),
    "symmetric top RKN 6": (lambda: lievi.SymmetricTopSplitting(6), 6, True, symmetric_tops),
    "RKMK4": (lambda: lievi.RKMK4(), 4, False, any_problem),
    "RKMK5": (lambda: lievi.RKMK5(), 5, False, any_problem),
    "RKMK8": (lambda: lievi.RKMK8(), 8, False, any_problem),
}  # fmt: skip
DIFFRAX_SOLVERS = {"Tsit5": 5, "Dopri5": 5, "Dopri8": 8}


def steps_for(order, horizon, quick):
    """Step sizes: the high-order methods reach tight errors at larger steps (an order-4
    method with small error constants, `SymmetricTopSplitting(4)`, meets 1e-2 on the
    Lagrange top at h = 0.8, so order 4 starts there too)."""
    if quick:
        return [0.2, 0.1]
    if order >= 6:
        return [0.8, 0.4, 0.2, 0.1, 0.05]
    if horizon == "long":
        return [0.4, 0.2, 0.1, 0.05, 0.025] if order >= 4 else [0.1, 0.05, 0.025]
    return [0.8, 0.4, 0.2, 0.1, 0.05, 0.025] if order >= 4 else [0.2, 0.1, 0.05, 0.025, 0.0125]


def tolerances_for(horizon, quick):
    if quick:
        return [1e-6, 1e-9]
    return [1e-4, 1e-6, 1e-8, 1e-10, 1e-12] + ([1e-13] if horizon == "long" else [])


# ---- the problems -------------------------------------------------------------------------


def system_of(problem):
    spec = PROBLEMS[problem]
    moments = jnp.asarray(spec["moments"])
    if spec["gravity"]:
        return lievi.heavy_top(
            moments, MASS, jnp.asarray(RHO), GRAVITY, inertia_about="center_of_mass"
        )
    return lievi.RigidBody(moments)


def initial_states(problem, batch, seed=0):
    spec = PROBLEMS[problem]
    m0 = np.asarray(spec["m0"]) * (1 + 0.05 * np.random.default_rng(seed).normal(size=(batch, 3)))
    return np.asarray(lievi.SO3.exp(jnp.asarray(spec["tilt"], dtype=float))), m0


def sample_every(n, samples=SAMPLES):
    """Steps between saved states: every run saves `samples`, at the same times."""
    if n % samples:
        raise ValueError(f"{n} steps: use a step count that is a multiple of {samples}")
    return n // samples


def reference(problem, count, t1):
    system = system_of(problem)
    g0, m0 = initial_states(problem, count)
    ts = np.linspace(0.0, t1, SAMPLES + 1)
    gs, ms = [], []
    for k in range(count):
        g, m = lievi.reference_solution(system, jnp.asarray(g0), jnp.asarray(m0[k]), ts)
        gs.append(np.asarray(g)[1:])
        ms.append(np.asarray(m)[1:])
    return np.array(gs), np.array(ms)


def errors(problem, g, m, ref):
    """Each quantity's error, the largest over the reference bodies and the saved times.
    `g (B, K, 3, 3)`, `m (B, K, 3)`; `ref` the reference's `(g, m)` at the same times."""
    system, gravity = system_of(problem), PROBLEMS[problem]["gravity"]
    count = ref[0].shape[0]
    g, m = np.asarray(g[:count]), np.asarray(m[:count])
    g_ref, m_ref = ref
    chord = np.linalg.norm(g - g_ref, axis=(-2, -1)) / (2 * np.sqrt(2))
    attitude = 2 * np.arcsin(np.clip(chord, 0.0, 1.0))
    axis = np.linalg.norm(g[..., :, 2] - g_ref[..., :, 2], axis=-1)

    def invariants(g, m):
        g, m = jnp.asarray(g), jnp.asarray(m)
        J = np.asarray(lievi.diagnostics.spatial_momentum(system, g, m))
        return np.asarray(lievi.diagnostics.energy(system, g, m)), (J[..., 2:] if gravity else J)

    g0, m0 = initial_states(problem, count)
    (H, J), (H0, J0) = (
        invariants(g, m),
        invariants(np.broadcast_to(g0, (count, 1, 3, 3)), m0[:, None]),
    )
    energy = np.abs(H - H0) / np.abs(H0)
    momentum = np.linalg.norm(J - J0, axis=-1) / np.linalg.norm(m0[:, None], axis=-1)
    out = dict(attitude=attitude, axis=axis, energy=energy, momentum=momentum)
    return {k: float(np.max(v)) if np.all(np.isfinite(v)) else float("nan") for k, v in out.items()}


def best_cpu_seconds(fn, args, repeats):
    """Compiled ahead (`fn` is jitted), then the best process CPU time of `repeats` calls."""
    compiled = fn.lower(*args).compile()
    best, out = np.inf, None
    for _ in range(repeats):
        start = time.process_time()
        out = jax.block_until_ready(compiled(*args))
        best = min(best, time.process_time() - start)
    return out, best


# ---- lievi --------------------------------------------------------------------------------


def lievi_run(problem, method, h, batch, t1, repeats, integrator=None):
    """`method` by name (`LIEVI_METHODS`), or `integrator` itself where given."""
    system = system_of(problem)
    g0, m0 = initial_states(problem, batch)
    n = int(round(t1 / h))
    every = sample_every(n)
    integrator = LIEVI_METHODS[method][0]() if integrator is None else integrator

    @jax.jit
    def run(m0):
        sol = lievi.simulate_batch(
            system, integrator, jnp.asarray(g0), m0, h=h, n_steps=n, throw=False,
            save=lievi.Save(g=True, m=True, stats=False, every=every),
        )  # fmt: skip
        return sol.g[:, 1:], sol.m[:, 1:], sol.result

    (g, m, result), seconds = best_cpu_seconds(run, (jnp.asarray(m0),), repeats)
    return g, m, seconds, bool(np.all(np.asarray(result) == 0)), n // every


# ---- diffrax, the batch in the state --------------------------------------------------------


def strong_field(problem):
    """The field on the whole batch, `y (12, B)` = Π (3 rows) and g row-major (9 rows):
    `Π̇ = Π × Ω (+ mγ Γ × ρ, Γ the last row of g)`, `ġ = gΩ̂` (row i of g crossed with Ω).
    The fastest of the formulations timed (12 scalar rows stacked; a pytree `(Π, g)`; this,
    with and without `scan_kind="lax"`): slices of one array and `jnp.cross` on the rows."""
    inverse = jnp.asarray(1.0 / np.asarray(system_of(problem).inertia))[:, None]
    torque = jnp.asarray(MASS * GRAVITY * RHO)[:, None]
    gravity = PROBLEMS[problem]["gravity"]

    def field(t, y, args):
        Pi, g = y[:3], y[3:].reshape(3, 3, -1)
        omega = Pi * inverse
        dPi = jnp.cross(Pi, omega, axis=0)
        if gravity:
            dPi = dPi + jnp.cross(g[2], torque, axis=0)
        return jnp.concatenate([dPi, jnp.cross(g, omega[None], axis=1).reshape(9, -1)])

    return field


def step_control(knob, adaptive, t1):
    """diffrax's step arguments and `max_steps`: a PID controller at rtol = atol = `knob`,
    or constant steps of `knob`."""
    import diffrax

    if adaptive:
        control = dict(dt0=None, stepsize_controller=diffrax.PIDController(rtol=knob, atol=knob))
        return control, int(t1 * 1e4)
    return dict(dt0=knob, stepsize_controller=diffrax.ConstantStepSize()), int(round(t1 / knob))


def diffrax_run(problem, solver, knob, adaptive, batch, t1, repeats, final_only=False):
    """The strong baseline: one solve, the whole batch one `(12, B)` state."""
    import diffrax

    g0, m0 = initial_states(problem, batch)
    y0 = np.concatenate([m0.T, np.broadcast_to(g0.reshape(9, 1), (9, batch))])
    ts = saved_times(t1)
    term = diffrax.ODETerm(strong_field(problem))
    saveat = diffrax.SaveAt(t1=True) if final_only else diffrax.SaveAt(ts=ts)
    ts = ts[-1:] if final_only else ts
    control, max_steps = step_control(knob, adaptive, t1)

    @jax.jit
    def run(y0):
        sol = diffrax.diffeqsolve(
            term, getattr(diffrax, solver)(),
            t0=0.0, t1=t1, y0=y0, saveat=saveat, max_steps=max_steps,
            adjoint=diffrax.ForwardMode(), throw=False, **control,
        )  # fmt: skip
        return sol.ys, sol.result == diffrax.RESULTS.successful

    (ys, ok), seconds = best_cpu_seconds(run, (jnp.asarray(y0),), repeats)
    ys = np.asarray(ys)  # (K, 12, B)
    m = ys[:, :3].transpose(2, 0, 1)
    g = ys[:, 3:].reshape(len(ts), 3, 3, batch).transpose(3, 0, 1, 2)
    return g, m, seconds, bool(ok), len(ts)


def saved_times(t1):
    """The `SAMPLES` times every run saves (not the start)."""
    return jnp.linspace(0.0, t1, SAMPLES + 1)[1:]


def independent_runner(problem, solver, h, batch, t1, repeats):
    """Written apart from `strong_field`, as a user would: the batch in a pytree state
    `(Π (3, B), g (3, 3, B))`, diffrax's default options (checkpointed adjoint, `throw`),
    the final state only."""
    import diffrax

    spec = PROBLEMS[problem]
    inverse = 1.0 / np.asarray(system_of(problem).inertia)[:, None]
    torque = np.array([0.0, 0.0, MASS * GRAVITY * RHO[2]])[:, None]

    def field(t, state, args):
        Pi, g = state
        omega = Pi * inverse
        dPi = jnp.cross(Pi, omega, axis=0)
        if spec["gravity"]:
            dPi = dPi + jnp.cross(g[2], torque, axis=0)
        return dPi, jnp.cross(g, omega[None], axis=1)

    g0, m0 = initial_states(problem, batch)
    state = (jnp.asarray(m0.T), jnp.broadcast_to(jnp.asarray(g0)[..., None], (3, 3, batch)))
    n = int(round(t1 / h))

    @jax.jit
    def run(state):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(field), getattr(diffrax, solver)(), t0=0.0, t1=t1, dt0=h, y0=state,
            stepsize_controller=diffrax.ConstantStepSize(), max_steps=n,
        )  # fmt: skip
        return sol.ys

    (Pi, g), seconds = best_cpu_seconds(run, (state,), repeats)
    return np.asarray(g)[-1].transpose(2, 0, 1), seconds


# ---- MuJoCo -------------------------------------------------------------------------------


def mjcf(problem, h, integrator):
    spec = PROBLEMS[problem]
    if spec["gravity"]:
        joint, gravity, pos = '<joint type="ball"/>', f"0 0 -{GRAVITY}", " ".join(map(str, RHO))
    else:
        joint, gravity, pos = "<freejoint/>", "0 0 0", "0 0 0"
    inertia = " ".join(map(str, spec["moments"]))
    return f"""
<mujoco>
  <option timestep="{h}" integrator="{integrator}" gravity="{gravity}"/>
  <worldbody><body name="body">{joint}
    <inertial pos="{pos}" mass="{MASS}" diaginertia="{inertia}"/>
  </body></worldbody>
</mujoco>"""


def mujoco_run(problem, integrator, h, batch, t1, repeats, threads):
    import mujoco
    from mujoco import rollout

    model = mujoco.MjModel.from_xml_string(mjcf(problem, h, integrator))
    datas = [mujoco.MjData(model) for _ in range(threads)]
    g0, m0 = initial_states(problem, batch)
    q0 = np.asarray(lievi.matrix_to_quaternion_wxyz(jnp.asarray(g0)))
    free = not PROBLEMS[problem]["gravity"]
    inertia = np.asarray(system_of(problem).inertia)  # about the joint
    spec, data = mujoco.mjtState.mjSTATE_FULLPHYSICS, datas[0]
    states = []
    for omega in m0 / inertia:  # body-frame angular velocity (free and ball joints)
        mujoco.mj_resetData(model, data)
        if free:
            data.qpos[3:7], data.qvel[3:6] = q0, omega
        else:
            data.qpos[:4], data.qvel[:3] = q0, omega
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)
        states.append(state)
    n = int(round(t1 / h))
    every = sample_every(n)
    best = np.inf
    for _ in range(repeats):
        state, saved = np.array(states), []
        start = time.process_time()
        for _ in range(n // every):
            out, _ = rollout.rollout(model, datas, state, nstep=every)
            state = out[:, -1, :]
            saved.append(state)
        best = min(best, time.process_time() - start)
    saved = np.stack(saved, axis=1)  # (B, K, state): time, qpos (7 | 4), qvel (6 | 3)
    nq = 7 if free else 4
    quaternion = saved[..., 4:8] if free else saved[..., 1:5]
    omega = saved[..., 1 + nq + 3 : 1 + nq + 6] if free else saved[..., 1 + nq : 1 + nq + 3]
    g = np.asarray(lievi.quaternion_wxyz_to_matrix(jnp.asarray(quaternion)))
    return g, omega * inertia, best, bool(np.all(np.isfinite(saved))), n // every


# ---- the sweep ----------------------------------------------------------------------------


def sweep(problem, horizon, t1, args, ref, meets_all):
    """Every run's cost and errors. `meets_all(row)`: whether a row meets every target of
    this horizon; it prunes the peers' dominated runs (`dominated`)."""
    rows, quick, spec = [], args.quick, PROBLEMS[problem]

    def record(family, method, knob, run, bodies, structure=False):
        try:
            g, m, seconds, ok, _ = run()
        except Exception as error:  # a method this problem does not support
            print(f"  {method:<26} {knob:>8.3g}  skipped: {type(error).__name__}: {error}"[:160])
            return None
        errs = errors(problem, g, m, ref) if ok else dict.fromkeys(QUANTITIES, float("nan"))
        cost = seconds / bodies * 1e6
        rows.append(dict(family=family, method=method, knob=knob, cost=cost, ok=ok,
                         structure_preserving=structure, **errs))  # fmt: skip
        shown = "  ".join(f"{q} {errs[q]:8.1e}" for q in QUANTITIES)
        print(f"  {method:<26} {knob:>8.3g}  {cost:9.3g} s/1e6 bodies  {shown}", flush=True)
        return rows[-1]

    def dominated(family, method, previous):
        """Whether the runs after `previous` in a sequence of rising cost (smaller steps,
        tighter tolerances) can be left out: `previous` already costs more than a run of
        `family` that meets every target, so no later one can be the family's cheapest at
        any target (the tables are unchanged; the tight `Tsit5` runs at T = 2·10⁴ cost
        minutes each)."""
        bound = min(
            (r["cost"] for r in rows if r["family"] == family and meets_all(r)), default=np.inf
        )
        if previous is None or previous["cost"] <= bound:
            return False
        print(f"  {method:<26} the rest skipped: dominated ({previous['cost']:.3g} > {bound:.3g})")
        return True

    B, r = args.batch, args.repeats
    for method, (_, order, structure, applies) in LIEVI_METHODS.items():
        if not applies(spec) or method not in (args.methods or LIEVI_METHODS):
            continue
        for h in steps_for(order, horizon, quick):
            run = partial(lievi_run, problem, method, h, B, t1, r)
            record("lievi", f"lievi {method}", h, run, B, structure)
    try:
        import diffrax  # noqa: F401
    except ImportError:
        print("  diffrax not installed: skipped")
    else:
        if args.knowledge:  # lievi's methods alone
            return rows
        # The order-8 solver first: its runs bound the others' (`dominated`).
        for solver, order in reversed(DIFFRAX_SOLVERS.items()):
            for adaptive, knobs in (
                (False, steps_for(order, horizon, quick)),
                (True, tolerances_for(horizon, quick)),
            ):
                name, previous = f"diffrax {solver} {'PID' if adaptive else 'constant'}", None
                for knob in knobs:
                    if dominated("diffrax", name, previous):
                        break
                    run = partial(diffrax_run, problem, solver, knob, adaptive, B, t1, r)
                    previous = record("diffrax", name, knob, run, B)
    if spec.get("mujoco", True) and not args.no_mujoco:
        try:
            import mujoco  # noqa: F401
        except ImportError:
            print("  mujoco not installed: skipped")
        else:
            mb = args.mujoco_batch
            integrators = ("RK4",) if quick else ("Euler", "implicitfast", "RK4")
            for integrator in integrators:
                for h in [x / 4 for x in steps_for(2, horizon, quick)][: 1 if quick else None]:
                    run = partial(mujoco_run, problem, integrator, h, mb, t1, r, args.threads)
                    record("MuJoCo", f"MuJoCo {integrator}", h, run, mb)
    return rows


def baseline_check(problem, args):
    """The strong diffrax against the independent runner, constant steps, T = 20."""
    out = {}
    for solver in ("Tsit5", "Dopri8"):
        h = 0.1
        repeats = max(3, args.repeats)  # a small difference to resolve: more calls
        g_s, _, strong, _, _ = diffrax_run(
            problem, solver, h, False, args.batch, T_SHORT, repeats, final_only=True
        )
        g_i, independent = independent_runner(problem, solver, h, args.batch, T_SHORT, repeats)
        out[solver] = dict(
            h=h, strong_cost=strong / args.batch * 1e6, independent_cost=independent / args.batch * 1e6,
            strong_over_independent=strong / independent,
            max_difference=float(np.max(np.abs(g_s[:, -1] - g_i))),
        )  # fmt: skip
        verdict = "ok" if strong <= 1.1 * independent else "STRONG BASELINE TOO SLOW"
        print(f"  baseline check {solver} h={h}: strong / independent = {strong / independent:.3f}"
              f" ({verdict}), final states agree to {out[solver]['max_difference']:.1e}")  # fmt: skip
    return out


def meets(target, quantities, row):
    """Whether a run met `target` on every quantity named."""
    return row["ok"] and all(row[q] <= target for q in quantities)


def summary(rows, targets, quantities):
    """Per target: the cheapest run of each family meeting it on every quantity named, the
    cheapest structure-preserving lievi run, and diffrax's cost over each lievi one."""
    table = {}
    for target in targets:

        def best(select, target=target):
            hits = [r for r in rows if select(r) and meets(target, quantities, r)]
            return min(hits, key=lambda r: r["cost"]) if hits else None

        entry = {}
        for name, select in (
            ("lievi", lambda r: r["family"] == "lievi"),
            ("lievi structure-preserving", lambda r: r["family"] == "lievi" and r["structure_preserving"]),
            ("diffrax", lambda r: r["family"] == "diffrax"),
            ("MuJoCo", lambda r: r["family"] == "MuJoCo"),
        ):  # fmt: skip
            hit = best(select)
            if hit:
                entry[name] = {k: hit[k] for k in ("method", "knob", "cost")}
        for name in ("lievi", "lievi structure-preserving"):
            if name in entry and "diffrax" in entry:
                entry[f"diffrax / {name}"] = entry["diffrax"]["cost"] / entry[name]["cost"]
        table[f"{target:.0e}"] = entry
    return table


def print_summary(table):
    for target, entry in table.items():

        def cell(name, entry=entry):
            e = entry.get(name)
            return f"{e['cost']:.3g} ({e['method']}, {e['knob']:g})" if e else "—"

        ratios = "  ".join(
            f"{k}: {v:.2g}×" for k, v in entry.items() if k.startswith(("diffrax /", "MuJoCo /"))
        )
        print(f"  {target}: lievi {cell('lievi')} | structure-preserving "
              f"{cell('lievi structure-preserving')} | diffrax {cell('diffrax')} | MuJoCo "
              f"{cell('MuJoCo')}  {ratios}")  # fmt: skip


def plot(results, path):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(p, h) for p in results["problems"] for h in results["problems"][p]]
    if not panels:  # the per-step cost table alone: nothing to plot
        return
    fig, axes = plt.subplots(1, len(panels), figsize=(5.5 * len(panels), 4.5), squeeze=False)
    for ax, (problem, horizon) in zip(axes[0], panels):
        data = results["problems"][problem][horizon]
        for method in sorted({r["method"] for r in data["rows"]}):
            rows = [r for r in data["rows"] if r["method"] == method]
            error = [max(r.get(q, np.nan) for q in data["quantities"]) for r in rows]
            keep = [i for i, e in enumerate(error) if np.isfinite(e)]
            if not keep:
                continue
            style = "-o" if method.startswith("lievi") else ("--s" if "diffrax" in method else ":^")
            ax.loglog([rows[i]["cost"] for i in keep], [error[i] for i in keep], style,
                      label=method, ms=3)  # fmt: skip
        unit = data.get("cost_unit", "CPU seconds per million bodies")
        ax.set_xlabel(f"{unit} (T = {data['T']:g})")
        ax.set_ylabel("largest error: " + ", ".join(data["quantities"]))
        ax.set_title(f"{problem}, T = {data['T']:g}")
        ax.grid(True, which="both", alpha=0.3)
    axes[0][-1].legend(fontsize=6, loc="lower left")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)  # `--coupled` plots after every run


# ---- articulated bodies (`--articulated`) ---------------------------------------------------
#
# The triple spherical pendulum and the 5-link hinge chain of tests/articulated_problems.py
# (a pivot at the world origin, gravity 9.81), each body of the batch with its own initial
# momentum (the problem's times `1 + 0.05·noise`, projected onto the joints). lievi: RATTLE
# and its compositions. diffrax: the index-reduced Newton–Euler equations with Lagrange
# multipliers of tests/articulated_problems.py (`reference_rhs`, maximal coordinates, the
# KKT system solved at every evaluation), the whole batch one `(B, 18N)` state. MuJoCo:
# the same chain in joint coordinates (an MJCF built here), `rollout`. Errors over the
# first `--reference` bodies: `pose` (the largest rotation angle between a body's attitude
# and the reference's, or distance between centres of mass over the link length, at the
# final time), `energy` (relative, largest over `SAMPLES` times), `momentum` (the vertical
# angular momentum about the pivot, relative to the largest body momentum, where it is
# conserved: the ball-jointed pendulum), and `joints` (the largest joint defect over the
# link length; MuJoCo's is zero by construction).

sys.path.insert(0, str(pathlib.Path(__file__).resolve().parent.parent / "tests"))
CHAINS = ("triple pendulum", "hinge chain")
CHAIN_T_SHORT = 2.0
CHAIN_JOINTS = 1e-10  # a long run counts only if its joints hold to this, relative
# name: (integrator, order, structure-preserving): RATTLE and its compositions are
# variational; the RKMK methods explicit, projected onto the joints after each step.
LIEVI_CHAIN_METHODS = {
    "RATTLE": (lambda: lievi.RATTLE(), 2, True),
    "RATTLE ∘ 4": (lambda: lievi.Composition(lievi.RATTLE(), order=4), 4, True),
    "RATTLE ∘ 4 Suzuki": (lambda: lievi.Composition(lievi.RATTLE(), 4, "suzuki"), 4, True),
    "RATTLE ∘ 6": (lambda: lievi.Composition(lievi.RATTLE(), order=6), 6, True),
    "RKMK4": (lambda: lievi.RKMK4(), 4, False),
    "RKMK8": (lambda: lievi.RKMK8(), 8, False),
}
# The per-step cost table (`chain_step_cost`): RATTLE's default iteration (the Jacobian
# once per step, solved by its structure) against Newton's method with the whole Jacobian
# by autodiff at every iteration, the same equations and root.
STEP_COST_METHODS = {
    "RATTLE, full Newton": (lambda: lievi.RATTLE(full_newton=True), 2),
    "RATTLE": (lambda: lievi.RATTLE(), 2),
}
STEP_COST_H, STEP_COST_STEPS = 0.01, 100


def chain_problem(problem):
    import articulated_problems as ap

    return ap.triple_pendulum() if problem == "triple pendulum" else ap.hinge_chain(5)


def chain_states(problem, batch, seed=0):
    """`(system, g0 (N, 4, 4), m0 (B, N, 6))`: one pose, perturbed momenta on the joints."""
    system, g0, m0 = chain_problem(problem)
    noise = np.random.default_rng(seed).normal(size=(batch, *m0.shape))
    m = jnp.asarray(m0) * (1 + 0.05 * noise)
    m = jax.jit(jax.vmap(system.project_momentum, (None, 0)))(g0, m)
    return system, np.asarray(g0), np.asarray(m)


def chain_steps(order, horizon, quick):
    if quick:
        return [0.02, 0.01]
    if horizon == "long":
        # The compositions' longest stage at h = 0.04 (the triple jump's −1.7h, Kahan–Li's)
        # is beyond RATTLE's iteration on these chains: such runs end in
        # `newton_not_converged` and cost as much as a successful one.
        if order >= 8:
            return [0.08, 0.04, 0.02]
        return [0.02, 0.01] if order >= 4 else [0.02, 0.01, 0.005]
    if order >= 8:
        return [0.08, 0.04, 0.02, 0.01]
    return [0.04, 0.02, 0.01, 0.005] if order >= 4 else [0.01, 0.005, 0.0025, 0.00125]


def chain_diffrax_runs(horizon, quick):
    """`(solver, tolerance)` pairs. At the long horizon `Dopri8` at 1e-12 alone: the
    maximal-coordinate ODE lets the joints drift (at T = 10, about 15 × the tolerance),
    so no looser run can keep them within `CHAIN_JOINTS` over T = 2·10³, and each costs
    minutes per body; `Tsit5` is the weaker of the two at tight tolerances."""
    if quick:
        return [("Dopri8", tol) for tol in tolerances_for(horizon, quick)]
    if horizon == "long":
        return [("Dopri8", 1e-12)]
    return [(s, tol) for s in ("Tsit5", "Dopri8") for tol in tolerances_for(horizon, quick)]


def chain_mujoco_steps(integrator, horizon, quick):
    """Half the order-4 steps; at the long horizon `RK4` goes on down to h = 0.00125, where
    its energy drift over T = 2·10³ first reaches the smallest targets (at T = 10 and
    h = 0.005 it is about 1.5e-7, growing linearly with T and as h⁴)."""
    steps = [x / 2 for x in chain_steps(4, horizon, quick)]
    if horizon == "long" and integrator == "RK4" and not quick:
        steps += [steps[-1] / 2, steps[-1] / 4]
    return steps


def chain_reference(problem, count, t1):
    """DOP853 (rtol = atol = 1e-13) of the Newton–Euler equations: `(R, x)` at `t1`."""
    import articulated_problems as ap
    from scipy.integrate import solve_ivp

    system, g0, m0 = chain_states(problem, count)
    rhs = ap.reference_rhs(system)
    R, x = [], []
    for k in range(count):
        y0 = np.asarray(ap.reference_state(system, jnp.asarray(g0), jnp.asarray(m0[k])))
        sol = solve_ivp(lambda t, y: np.asarray(rhs(jnp.asarray(y))), (0.0, t1), y0,
                        method="DOP853", rtol=1e-13, atol=1e-13)  # fmt: skip
        Rk, xk = ap.reference_poses(system, sol.y[:, -1])
        R.append(np.asarray(Rk))
        x.append(np.asarray(xk))
    return np.array(R), np.array(x)


def chain_errors(problem, g, m, ref, count):
    """`g (B, K, N, 4, 4)`, `m (B, K, N, 6)` at the `SAMPLES` times; `ref` the reference's
    final `(R, x)` (None at the long horizon). Over the first `count` bodies."""
    system, g0, m0 = chain_states(problem, count)
    g, m = jnp.asarray(np.asarray(g[:count])), jnp.asarray(np.asarray(m[:count]))
    start = jnp.broadcast_to(jnp.asarray(g0), (count, *g0.shape))
    energy = lievi.diagnostics.energy(system, g, m)
    H0 = lievi.diagnostics.energy(system, start, jnp.asarray(m0))[:, None]
    out = dict(energy=float(np.max(np.abs(energy - H0) / np.abs(H0))))
    if problem == "triple pendulum":
        L = lievi.diagnostics.total_momentum(system, g, m)[..., 2]
        L0 = lievi.diagnostics.total_momentum(system, start, jnp.asarray(m0))[:, 2]
        out["momentum"] = float(np.max(np.abs(L - L0[:, None])) / np.max(np.abs(m0)))
    defects = jax.jit(jax.vmap(jax.vmap(system.joint_defect)))(g)
    out["joints"] = float(np.max(defects))
    if ref is not None:
        R, x = np.asarray(g[:, -1, :, :3, :3]), np.asarray(g[:, -1, :, :3, 3])
        chord = np.linalg.norm(R - ref[0], axis=(-2, -1)) / (2 * np.sqrt(2))
        angle = 2 * np.arcsin(np.clip(chord, 0.0, 1.0))
        apart = np.linalg.norm(x - ref[1], axis=-1) / float(system.length_scale())
        out["pose"] = float(max(np.max(angle), np.max(apart)))
    return {k: v if np.isfinite(v) else float("nan") for k, v in out.items()}


def chain_lievi_run(problem, method, h, batch, t1, repeats):
    """Eager `simulate_batch` (its programs compiled by a first call), the best CPU time."""
    system, g0, m0 = chain_states(problem, batch)
    n = int(round(t1 / h))
    integrator = (LIEVI_CHAIN_METHODS | STEP_COST_METHODS)[method][0]()
    g0 = jnp.broadcast_to(jnp.asarray(g0), (batch, *g0.shape))

    def run(n=n):
        sol = lievi.simulate_batch(
            system, integrator, g0, jnp.asarray(m0), h=h, n_steps=n,
            save=lievi.Save(g=True, m=True, stats=False, every=sample_every(n)),
            throw=False,
        )  # fmt: skip
        return jax.block_until_ready((sol.g[:, 1:], sol.m[:, 1:], sol.result))

    run(SAMPLES)  # compiles the programs of any horizon (a new `n_steps` compiles nothing)
    best = np.inf
    for _ in range(repeats):
        start = time.process_time()
        g, m, result = run()
        best = min(best, time.process_time() - start)
    return g, m, best, bool(np.all(np.asarray(result) == 0))


def chain_diffrax_run(problem, solver, knob, adaptive, batch, t1, repeats):
    """The Newton–Euler/Lagrange-multiplier ODE, the batch one `(B, 18N)` state."""
    import articulated_problems as ap
    import diffrax

    system, g0, m0 = chain_states(problem, batch)
    n = system.n_bodies
    rhs = jax.vmap(ap.reference_rhs(system))
    y0 = jax.vmap(ap.reference_state, (None, None, 0))(system, jnp.asarray(g0), jnp.asarray(m0))
    control, max_steps = step_control(knob, adaptive, t1)

    @jax.jit
    def run(y0):
        sol = diffrax.diffeqsolve(
            diffrax.ODETerm(lambda t, y, args: rhs(y)), getattr(diffrax, solver)(),
            t0=0.0, t1=t1, y0=y0, saveat=diffrax.SaveAt(ts=saved_times(t1)),
            max_steps=max_steps, adjoint=diffrax.ForwardMode(), throw=False, **control,
        )  # fmt: skip
        return sol.ys, sol.result == diffrax.RESULTS.successful

    (ys, ok), seconds = best_cpu_seconds(run, (y0,), repeats)
    ys = np.asarray(ys).transpose(1, 0, 2).reshape(batch, SAMPLES, n, 18)  # (B, K, N, 18)
    g = np.zeros((batch, SAMPLES, n, 4, 4))
    g[..., :3, :3] = ys[..., :9].reshape(batch, SAMPLES, n, 3, 3)
    g[..., :3, 3], g[..., 3, 3] = ys[..., 9:12], 1.0
    m = np.asarray(jax.vmap(jax.vmap(system.legendre))(jnp.asarray(ys[..., 12:])))
    return g, m, seconds, bool(ok)


def chain_mjcf(problem, h, integrator):
    """The chain in joint coordinates: each body's frame at its centre of mass, placed at
    the joints' rest configuration (every relative rotation the identity)."""
    system, _, _ = chain_problem(problem)
    inertia = np.asarray(system.inertia)
    xml = ""
    for i in reversed(range(system.n_bodies)):
        joint = system.joints[i]
        parent_point, child_point = np.asarray(joint.parent_point), np.asarray(joint.child_point)
        pos = " ".join(map(str, parent_point - child_point))
        anchor = " ".join(map(str, child_point))
        if isinstance(joint, lievi.HingeJoint):
            axis = " ".join(map(str, np.asarray(joint.axis)))
            kind = f'<joint type="hinge" pos="{anchor}" axis="{axis}"/>'
        else:
            kind = f'<joint type="ball" pos="{anchor}"/>'
        body = " ".join(map(str, inertia[i]))
        xml = (f'<body pos="{pos}">{kind}<inertial pos="0 0 0" mass="{float(system.mass[i])}" '
               f'diaginertia="{body}"/>{xml}</body>')  # fmt: skip
    return f"""
<mujoco>
  <option timestep="{h}" integrator="{integrator}" gravity="0 0 -9.81"/>
  <worldbody>{xml}</worldbody>
</mujoco>"""


def chain_to_mujoco(system, g, m):
    """Joint coordinates of maximal-coordinate states with one pose `g` `(N, 4, 4)` and a
    batch of momenta `m` `(B, N, 6)`: `(qpos (nq,), qvel (B, nv))`. The velocities of the
    whole batch in one compiled call: 3.8 s for 4096 hinge chains, compile included, where
    a call per chain took 2.5 ms each (and minutes at 4096 while `lievi.SO3.log` ran its
    operations one by one)."""
    R = g[:, :3, :3]
    xi = np.asarray(jax.jit(jax.vmap(system.velocity))(jnp.asarray(m)))
    w = np.einsum("nij,bnj->bni", R, xi[..., :3])  # world angular velocities
    qpos, qvel = [], []
    for i, (p, joint) in enumerate(zip(system.parents, system.joints)):
        Rp, wp = (np.eye(3), 0.0) if p == -1 else (R[p], w[:, p])
        relative = Rp.T @ R[i]
        if isinstance(joint, lievi.HingeJoint):
            axis = np.asarray(joint.axis) / np.linalg.norm(joint.axis)
            qpos.append([float(np.asarray(lievi.SO3.log(jnp.asarray(relative))) @ axis)])
            qvel.append(((w[:, i] - wp) @ (R[i] @ axis))[:, None])
        else:
            qpos.append(np.asarray(lievi.matrix_to_quaternion_wxyz(jnp.asarray(relative))))
            qvel.append((w[:, i] - wp) @ R[i])  # R[i]ᵀ(w_i − w_p), each chain
    return np.concatenate(qpos), np.concatenate(qvel, axis=1)


def chain_mujoco_run(problem, integrator, h, batch, t1, repeats, threads, count):
    import mujoco
    from mujoco import rollout

    system, g0, m0 = chain_states(problem, batch)
    model = mujoco.MjModel.from_xml_string(chain_mjcf(problem, h, integrator))
    datas = [mujoco.MjData(model) for _ in range(threads)]
    spec, data = mujoco.mjtState.mjSTATE_FULLPHYSICS, datas[0]
    states = []
    qpos, qvel = chain_to_mujoco(system, g0, m0)
    for k in range(batch):
        mujoco.mj_resetData(model, data)
        data.qpos[:], data.qvel[:] = qpos, qvel[k]
        state = np.empty(mujoco.mj_stateSize(model, spec))
        mujoco.mj_getState(model, data, state, spec)
        states.append(state)
    n = int(round(t1 / h))
    every = sample_every(n)
    best = np.inf
    for _ in range(repeats):
        state, saved = np.array(states), []
        start = time.process_time()
        for _ in range(n // every):
            out, _ = rollout.rollout(model, datas, state, nstep=every)
            state = out[:, -1, :]
            saved.append(state[:count])
        best = min(best, time.process_time() - start)
    # Back to maximal coordinates for the reference bodies: poses and body-frame velocities.
    nb = system.n_bodies
    g = np.zeros((count, len(saved), nb, 4, 4))
    xi = np.zeros((count, len(saved), nb, 6))
    velocity = np.zeros(6)
    for s, block in enumerate(saved):
        for k in range(count):
            mujoco.mj_setState(model, data, block[k], spec)
            mujoco.mj_forward(model, data)
            for i in range(nb):
                g[k, s, i, :3, :3] = data.xmat[i + 1].reshape(3, 3)
                g[k, s, i, :3, 3], g[k, s, i, 3, 3] = data.xpos[i + 1], 1.0
                mujoco.mj_objectVelocity(model, data, mujoco.mjtObj.mjOBJ_BODY, i + 1, velocity, 1)
                xi[k, s, i] = velocity
    m = np.asarray(jax.vmap(jax.vmap(system.legendre))(jnp.asarray(xi)))
    return g, m, best, bool(np.all(np.isfinite(np.stack(saved))))


def chain_sweep(problem, horizon, t1, args, ref):
    rows, quick = [], args.quick
    count = args.reference

    def record(family, method, knob, run, bodies, structure=False):
        try:
            g, m, seconds, ok = run()
        except Exception as error:
            print(f"  {method:<26} {knob:>8.3g}  skipped: {type(error).__name__}: {error}"[:160])
            return
        errs = chain_errors(problem, g, m, ref, count) if ok else {}
        cost = seconds / bodies * 1e6
        rows.append(dict(family=family, method=method, knob=knob, cost=cost, ok=ok,
                         structure_preserving=structure, **errs))  # fmt: skip
        shown = "  ".join(f"{q} {v:8.1e}" for q, v in errs.items())
        print(f"  {method:<26} {knob:>8.3g}  {cost:9.3g} s/1e6 bodies  {shown}", flush=True)

    B, r = args.batch, args.repeats
    # A smoke run: the cheapest method of each order up to 4, one diffrax solver.
    methods = list(LIEVI_CHAIN_METHODS)[:2] if quick else list(LIEVI_CHAIN_METHODS)
    methods = [m for m in methods if m in (args.chain_methods or methods)]
    for method in methods:
        _, order, structure = LIEVI_CHAIN_METHODS[method]
        for h in chain_steps(order, horizon, quick):
            run = partial(chain_lievi_run, problem, method, h, B, t1, r)
            record("lievi", f"lievi {method}", h, run, B, structure)
    for solver, tol in [] if args.no_diffrax else chain_diffrax_runs(horizon, quick):
        run = partial(chain_diffrax_run, problem, solver, tol, True, B, t1, r)
        record("diffrax", f"diffrax {solver} PID", tol, run, B)
    if not args.no_mujoco:
        integrators = ("RK4",) if quick else ("implicitfast", "RK4")
        for integrator in integrators:
            for h in chain_mujoco_steps(integrator, horizon, quick):
                run = partial(chain_mujoco_run, problem, integrator, h, args.mujoco_batch, t1,
                              r, args.threads, count)  # fmt: skip
                record("MuJoCo", f"MuJoCo {integrator}", h, run, args.mujoco_batch)
    return rows


def chain_step_cost(problem, args):
    """CPU microseconds per chain and step (`STEP_COST_STEPS` steps of h = `STEP_COST_H`;
    `SAMPLES` steps at a batch above 16) at each `--step-cost-batches` (default `--batch`),
    lievi and MuJoCo's RK4 at the same step and batch (Newton's method at the smallest
    batch only), each the best of at least three timed calls, all in this one process:
    the ratios are read at one machine load."""
    repeats, table = max(args.repeats, 3), {}
    batches = args.step_cost_batches or [args.batch]
    for batch in batches:
        steps = STEP_COST_STEPS if batch <= 16 else SAMPLES
        t1, cost = STEP_COST_H * steps, {}
        for method in STEP_COST_METHODS:
            if method != "RATTLE" and batch != min(batches):
                continue
            _, _, seconds, ok = chain_lievi_run(problem, method, STEP_COST_H, batch, t1, repeats)
            cost[method] = seconds / (batch * steps) * 1e6 if ok else float("nan")
        if not args.no_mujoco:
            _, _, seconds, _ = chain_mujoco_run(problem, "RK4", STEP_COST_H, batch, t1,
                                                repeats, args.threads, 1)  # fmt: skip
            cost["MuJoCo RK4"] = seconds / (batch * steps) * 1e6
        print(f"  batch {batch}, per chain-step: "
              + "  ".join(f"{k} {v:.3g} µs" for k, v in cost.items()))  # fmt: skip
        ratios = {f"{k} / RATTLE": v / cost["RATTLE"] for k, v in cost.items() if k != "RATTLE"}
        print("  " + "  ".join(f"{k} {v:.3g}" for k, v in ratios.items()), flush=True)
        table[str(batch)] = dict(h=STEP_COST_H, n_steps=steps, microseconds=cost, ratios=ratios,
                                 load_average=os.getloadavg())  # fmt: skip
    return table


def chain_quantities(problem, horizon):
    if horizon == "short":
        return ("pose",)
    return ("energy", "momentum") if problem == "triple pendulum" else ("energy",)


def chain_summary(rows, targets, quantities, horizon):
    """`summary`, a run counting at the long horizon only if its joints held (MuJoCo's
    joint coordinates hold them by construction)."""
    held = [
        r for r in rows
        if horizon == "short" or r["family"] == "MuJoCo" or r.get("joints", 1.0) <= CHAIN_JOINTS
    ]  # fmt: skip
    table = summary(held, targets, quantities)
    for entry in table.values():
        for name in ("lievi", "lievi structure-preserving"):
            if name in entry and "MuJoCo" in entry:
                entry[f"MuJoCo / {name}"] = entry["MuJoCo"]["cost"] / entry[name]["cost"]
    return table


# ---- suggest_integrator's knowledge ---------------------------------------------------------

# The benchmark's problems and methods in `lievi/_suggest_knowledge.py` (its `METHODS`).
KNOWLEDGE_PROBLEMS = ("free body", "HLW body", "heavy top", "Lagrange top")
KNOWLEDGE_METHODS = ("splitting", "splitting ∘ 4", "splitting ∘ 6", "splitting ∘ 8",
                     "RKMK4", "RKMK5", "RKMK8", "symmetric top RKN 4", "symmetric top RKN 6")  # fmt: skip
# The table's quantities: the attitude is the trajectory's on the integrable problems only
# (the heavy top's is chaotic beyond short horizons).
KNOWLEDGE_QUANTITIES = ("attitude", "energy", "momentum")
ROUNDOFF_LEVEL = 1e-12


def knowledge(results):
    """`lievi/_suggest_knowledge.py`'s `TABLE` from the runs: for each class (the problems
    pooled by `problem_class`), method and quantity, `(C, a, floor)` of `error ≈ C (ωh)^p
    (ωT)^a + floor` by least squares on the logarithms (`p` the method's order), and the
    cheapest measured seconds per body-step. A quantity whose errors all stay below
    `ROUNDOFF_LEVEL` is kept to round-off: `C = 0`, `floor` their largest. Otherwise the
    errors between 1e-12 (the reference's accuracy) and 0.1 (not asymptotic) are fitted,
    `C` raised to bound every one of them; the floor is the smallest error reached where
    that is below 1e-11 (the reference's accuracy, or round-off), else 0."""
    from lievi._suggest_knowledge import problem_class

    points, costs = {}, {}
    for problem, horizons in results["problems"].items():
        system = system_of(problem)
        g0, m0 = initial_states(problem, 1)
        known = problem_class(system, jnp.asarray(g0), jnp.asarray(m0[0]))
        omega = known.frequency
        for run in horizons.values():
            T = run["T"]
            for row in run["rows"]:
                method = row["method"].removeprefix("lievi ")
                if row["family"] != "lievi" or method not in KNOWLEDGE_METHODS or not row["ok"]:
                    continue
                key = (known.name, method)
                n_steps = T / row["knob"]
                costs[key] = min(costs.get(key, np.inf), row["cost"] * 1e-6 / n_steps)
                for q in KNOWLEDGE_QUANTITIES:
                    if q == "attitude" and known.chaotic:
                        continue
                    points.setdefault((*key, q), []).append(
                        (omega * row["knob"], omega * T, row[q])
                    )
    table = {}
    for (cls, method), cost in sorted(costs.items()):
        order = LIEVI_METHODS[method][1]
        errors = {}
        for q in KNOWLEDGE_QUANTITIES:
            data = np.array(points.get((cls, method, q), []), float)
            if len(data) == 0:
                continue
            e = data[:, 2]
            if e.max() <= ROUNDOFF_LEVEL:
                errors[q] = (0.0, 0.0, float(e.max()))
                continue
            # The asymptotic points: above the reference's accuracy, below O(1) errors.
            fit = data[(e > 1e-12) & (e < 0.1)]
            if len(fit) == 0:
                continue
            y = np.log(fit[:, 2]) - order * np.log(fit[:, 0])
            if len(np.unique(fit[:, 1])) > 1:
                X = np.stack([np.ones(len(fit)), np.log(fit[:, 1])], axis=1)
                (logC, a), *_ = np.linalg.lstsq(X, y, rcond=None)
            else:
                logC, a = float(np.mean(y - np.log(fit[:, 1]))), 1.0
            # The constant that bounds every fitted point (the model is an upper estimate).
            logC = float(np.max(y - a * np.log(fit[:, 1])))
            # The floor: the reference's accuracy where a run reached it, else none.
            floor = float(e.min()) if e.min() < 1e-11 else 0.0
            errors[q] = (float(np.exp(logC)), round(float(a), 3), floor)
        # The model holds where it was fitted: no step larger than the benchmark's.
        largest = max(x for q in KNOWLEDGE_QUANTITIES for x, *_ in points.get((cls, method, q), []))
        table[(cls, method)] = {
            "order": order,
            "seconds_per_body_step": float(cost),
            "largest_omega_h": float(largest),
            "errors": errors,
        }
    return table


# ---- the heavy top's free flow: what a more accurate one inside the splitting would give ----

# (outer order, composition stages, step counts T/h = 25·m): the splitting kick – free – kick,
# alone and composed (Kahan–Li's default schemes).
FREE_FLOW_OUTER = {2: (1, (8, 16, 32, 64, 128, 256)), 4: (3, (2, 4, 8, 16, 32, 64, 128)),
                   6: (9, (1, 2, 3, 4, 6, 8, 12, 16)), 8: (17, (1, 2, 3, 4, 6, 8))}  # fmt: skip
FREE_FLOW_TARGETS = (1e-4, 1e-6, 1e-8)


class ExactFreeFlowKick(lievi.AbstractKickIntegrator):
    """Kick – free flow – kick with the free rigid body's flow to round-off (`substeps`
    steps of `Composition(LiePoissonSplitting(), 8)`): what any more accurate Lie–Poisson
    free flow inside the heavy top's splitting (the preprocessed Moser–Veselov step, the
    elliptic-function flow) could at best give. For its errors only: its cost is not
    that of such a flow."""

    substeps: int = 4

    def order(self):
        return 2

    def is_symmetric(self):
        return True

    def free_step(self, system, g, m, h):
        free, inner = (
            lievi.RigidBody(system.inertia),
            lievi.Composition(lievi.LiePoissonSplitting(), 8),
        )
        for _ in range(self.substeps):
            g, m, info = inner.step(free, g, m, h / self.substeps)
        return g, m, info


def cost_at(points, target):
    """The cost at which a method's error reaches `target`, interpolated log–log between
    its runs `(cost, error)`; `None` if no run reaches it."""
    points = sorted((c, e) for c, e in points if np.isfinite(e))
    for (c0, e0), (c1, e1) in zip(points, points[1:]):
        if e0 > target >= e1:
            w = np.log(e0 / target) / np.log(e0 / e1)
            return float(np.exp((1 - w) * np.log(c0) + w * np.log(c1)))
    return points[0][0] if points and points[0][1] <= target else None


def stage_costs(problem, batch, t1, rounds):
    """ns per body and stage of the splitting and of kick – DMV – kick (`MoserVeselov`),
    alone (h = 0.0125) and in `Composition(…, 8)` (h = 0.2), best of interleaved rounds."""
    system, (g0, m0) = system_of(problem), initial_states(problem, batch)
    m0 = jnp.asarray(m0)
    programs = {}
    for label, method, h, stages in (
        ("splitting", lievi.LiePoissonSplitting(), 0.0125, 1),
        ("kick-DMV-kick", lievi.MoserVeselov(), 0.0125, 1),
        ("splitting ∘ 8", lievi.Composition(lievi.LiePoissonSplitting(), 8), 0.2, 17),
        ("kick-DMV-kick ∘ 8", lievi.Composition(lievi.MoserVeselov(), 8), 0.2, 17),
    ):
        n = int(round(t1 / h))
        save = lievi.Save(g=True, m=True, stats=False, every=sample_every(n))
        run = jax.jit(
            partial(lievi.simulate_batch, system, method, jnp.asarray(g0), h=h, n_steps=n,
                    throw=False, save=save)
        )  # fmt: skip
        programs[label] = (run.lower(m0).compile(), batch * n * stages)
    best = dict.fromkeys(programs, np.inf)
    for _ in range(rounds):
        for label, (compiled, count) in programs.items():
            start = time.process_time()
            jax.block_until_ready(compiled(m0))
            best[label] = min(best[label], (time.process_time() - start) / count * 1e9)
    return best


def free_flow(args):
    """The heavy top at T = 20: attitude error at fixed h of the splitting with today's free
    flow (the axis splitting) and with an exact one, alone and composed; per body-step
    costs; cost to each target against diffrax `Dopri8` (batch in the state), same run."""
    problem, t1, B, r = "heavy top", T_SHORT, args.batch, args.repeats
    ref = reference(problem, args.reference, t1)
    out = dict(variants={})

    def compose(method, order):
        return method if order == 2 else lievi.Composition(method, order)

    for order, (stages, multiples) in FREE_FLOW_OUTER.items():
        today, exact = [], []
        for k in multiples:
            h = 0.8 / k
            n = int(round(t1 / h))
            method = compose(lievi.LiePoissonSplitting(), order)
            g, m, seconds, ok, _ = lievi_run(problem, None, h, B, t1, r, integrator=method)
            e = errors(problem, g, m, ref)["attitude"] if ok else float("nan")
            today.append(
                dict(h=h, cost=seconds / B * 1e6, per_step_ns=seconds / B / n * 1e9, attitude=e)
            )
            g, m, _, ok, _ = lievi_run(
                problem, None, h, args.reference, t1, 1, compose(ExactFreeFlowKick(), order)
            )
            exact.append(
                dict(h=h, attitude=errors(problem, g, m, ref)["attitude"] if ok else float("nan"))
            )
            print(f"  order {order} h={h:<7.4g} axis splitting {e:8.1e} ({today[-1]['per_step_ns']:5.0f} ns "
                  f"a body-step)  exact free flow {exact[-1]['attitude']:8.1e}", flush=True)  # fmt: skip
        out["variants"][order] = dict(stages=stages, axis_splitting=today, exact_free_flow=exact)
    # What a DMV-based free flow costs at least: a kick – DMV – kick stage on the fast path,
    # against a splitting stage, in interleaved rounds (a load-robust ratio); and the
    # preprocessed step's modified moments, which depend on the free body's energy and
    # Casimir — both changed by every kick, so needed anew at every stage.
    stage = stage_costs(problem, B, t1, max(r, 4))
    free, pmv = lievi.RigidBody(system_of(problem).inertia), lievi.PreprocessedMoserVeselov(8)
    moments = jax.jit(jax.vmap(lambda m: (lambda p: (p.alpha, p.beta))(pmv.init(free, m, 0.1))))
    _, seconds = best_cpu_seconds(moments, (jnp.asarray(initial_states(problem, B)[1]),), max(r, 3))
    stage["PMV(8) modified moments, one body"] = seconds / B * 1e9
    out["ns_per_body_stage"] = stage
    print("  ns per body and stage: " + ", ".join(f"{k} {v:.0f}" for k, v in stage.items()))
    dopri = []
    for k in (2, 4, 8, 16, 32):
        g, m, seconds, ok, _ = diffrax_run(problem, "Dopri8", 0.8 / k, False, B, t1, r)
        dopri.append(dict(knob=0.8 / k, adaptive=False, cost=seconds / B * 1e6,
                          attitude=errors(problem, g, m, ref)["attitude"] if ok else float("nan")))  # fmt: skip
    for tol in tolerances_for("short", False):
        g, m, seconds, ok, _ = diffrax_run(problem, "Dopri8", tol, True, B, t1, r)
        dopri.append(dict(knob=tol, adaptive=True, cost=seconds / B * 1e6,
                          attitude=errors(problem, g, m, ref)["attitude"] if ok else float("nan")))  # fmt: skip
    out["dopri8"] = dopri
    table = {}
    for target in FREE_FLOW_TARGETS:
        entry = {}
        for adaptive in (False, True):
            c = cost_at(
                [(d["cost"], d["attitude"]) for d in dopri if d["adaptive"] == adaptive], target
            )
            if c is not None:
                entry["Dopri8"] = min(entry.get("Dopri8", c), c)
        for order, v in out["variants"].items():
            today = cost_at([(d["cost"], d["attitude"]) for d in v["axis_splitting"]], target)
            n_today = cost_at([(t1 / d["h"], d["attitude"]) for d in v["axis_splitting"]], target)
            n_exact = cost_at([(t1 / d["h"], d["attitude"]) for d in v["exact_free_flow"]], target)
            if None in (today, n_today, n_exact):
                continue
            # Steps saved by an exact free flow = the cost of a stage, relative to a splitting
            # stage, at which it only breaks even; at a DMV stage's cost (no modified
            # moments: a lower bound for the preprocessed step) it would cost `at_dmv`.
            pair = (
                ("splitting", "kick-DMV-kick")
                if order == 2
                else ("splitting ∘ 8", "kick-DMV-kick ∘ 8")
            )
            at_dmv = today * n_exact / n_today * stage[pair[1]] / stage[pair[0]]
            entry[f"order {order}"] = dict(axis_splitting=today, steps_saved=n_today / n_exact,
                                           exact_free_flow_at_dmv_cost=at_dmv)  # fmt: skip
        table[f"{target:.0e}"] = entry
        cells = "  ".join(
            f"o{o[-1]}: {e['axis_splitting']:.3g} → {e['exact_free_flow_at_dmv_cost']:.3g} "
            f"(steps ÷{e['steps_saved']:.2f})"
            for o, e in entry.items() if o != "Dopri8"
        )  # fmt: skip
        dopri8 = entry.get("Dopri8", float("nan"))
        print(f"  {target:.0e} (s/1e6 bodies): Dopri8 {dopri8:.3g}  {cells}")
    out["cost_to_target"] = table
    return out


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--batch", type=int, default=256)
    parser.add_argument("--mujoco-batch", type=int, default=64)
    parser.add_argument("--reference", type=int, default=8, help="bodies checked against DOP853")
    parser.add_argument("--problems", nargs="+", default=list(PROBLEMS), choices=list(PROBLEMS))
    parser.add_argument(
        "--horizons", nargs="+", default=["short", "long"], choices=["short", "long"]
    )
    parser.add_argument("--long-T", type=float, default=2e4, help="the long horizon")
    parser.add_argument("--repeats", type=int, default=2, help="timed calls per run (best kept)")
    parser.add_argument("--no-mujoco", action="store_true")
    parser.add_argument(
        "--no-diffrax", action="store_true", help="with --articulated: no diffrax runs"
    )
    parser.add_argument("--all-cores", action="store_true", help="do not pin to one core")
    parser.add_argument("--quick", action="store_true", help="two steps, batch 64, T_long = 200")
    parser.add_argument(
        "--methods", nargs="+", default=None, choices=list(LIEVI_METHODS),
        help="lievi methods to run (default: all)",
    )  # fmt: skip
    parser.add_argument(
        "--knowledge-from",
        nargs="+",
        default=None,
        metavar="JSON",
        help="fit and print suggest_integrator's table from these results files (e.g. a "
        "problem's short and long full-size runs) instead of running",
    )
    parser.add_argument(
        "--knowledge", action="store_true",
        help="fit and print suggest_integrator's table (lievi/_suggest_knowledge.py) from the "
        "runs: its problems and methods, long horizon at most 2000, lievi only",
    )  # fmt: skip
    parser.add_argument(
        "--articulated", action="store_true",
        help="the articulated chains (triple pendulum, 5-link hinge chain) instead",
    )  # fmt: skip
    parser.add_argument("--chains", nargs="+", default=list(CHAINS), choices=list(CHAINS))
    parser.add_argument(
        "--chain-methods", nargs="+", default=None, choices=list(LIEVI_CHAIN_METHODS),
        help="with --articulated: the lievi methods (default: all)",
    )  # fmt: skip
    parser.add_argument(
        "--free-flow", action="store_true",
        help="the heavy top at T = 20: today's splitting against one with an exact free flow",
    )  # fmt: skip
    parser.add_argument(
        "--step-cost-only", action="store_true",
        help="with --articulated: only the per chain-step cost table (RATTLE's iterations, MuJoCo)",
    )  # fmt: skip
    parser.add_argument(
        "--step-cost-batches", nargs="+", type=int, default=None,
        help="with --articulated: the batches of the per chain-step cost table (default --batch)",
    )  # fmt: skip
    parser.add_argument(
        "--coupled", nargs="+", default=None, choices=["binary", "water"],
        help="coupled rigid bodies at a long horizon, invariant targets "
        "(benchmarks/work_precision_coupled.py): the binary asteroid (--batch systems, "
        "--long-T), rigid water (--water-batch systems of --molecules, --water-T)",
    )  # fmt: skip
    parser.add_argument("--water-batch", type=int, default=1)
    parser.add_argument("--molecules", type=int, default=64)
    parser.add_argument("--water-T", type=float, default=2000.0)
    parser.add_argument(
        "--coupled-methods", nargs="+", default=None, help="with --coupled: lievi methods"
    )
    parser.add_argument("--check", action="store_true", help="with --coupled: the field check")
    parser.add_argument("--out", default=None, help="default work_precision[_articulated][_quick]")
    parser.add_argument("--outdir", default=str(pathlib.Path(__file__).parent / "results"))
    args = parser.parse_args()
    args.threads = os.cpu_count() if args.all_cores else 1
    if args.articulated:
        return main_articulated(args)
    if args.coupled:
        import work_precision_coupled

        return work_precision_coupled.main(args)
    if args.free_flow:
        load, start = os.getloadavg(), time.perf_counter()
        return save(free_flow(args), args, load, start, args.out or "work_precision_free_flow")
    if args.knowledge_from:
        return print_knowledge(merged_results(args.knowledge_from), args.outdir)
    if args.knowledge:
        args.problems = [p for p in args.problems if p in KNOWLEDGE_PROBLEMS]
        args.methods = args.methods or list(KNOWLEDGE_METHODS)
        args.no_mujoco, args.long_T = True, min(args.long_T, 2000.0)
    if args.quick:
        args.batch, args.mujoco_batch = min(args.batch, 64), min(args.mujoco_batch, 16)
        args.reference, args.long_T = min(args.reference, 4), min(args.long_T, 200.0)
        args.repeats = 1
    out = args.out or ("work_precision_quick" if args.quick else "work_precision")
    load, start = os.getloadavg(), time.perf_counter()
    results = {"problems": {}}
    for problem in args.problems:
        results["problems"][problem] = {}
        print(f"{problem}:")
        short = "short" in args.horizons and not args.knowledge
        check = baseline_check(problem, args) if short else None
        for horizon in args.horizons:
            t1 = T_SHORT if horizon == "short" else args.long_T
            quantities = ("attitude",) if horizon == "short" else PROBLEMS[problem]["long_targets"]
            targets = TARGETS_SHORT if horizon == "short" else TARGETS_LONG
            print(f" T = {t1:g}, batch {args.batch}, targets on {', '.join(quantities)}:")
            ref = reference(problem, args.reference, t1)
            rows = sweep(problem, horizon, t1, args, ref, partial(meets, min(targets), quantities))
            table = summary(rows, targets, quantities)
            print_summary(table)
            results["problems"][problem][horizon] = dict(
                T=t1, quantities=quantities, rows=rows, summary=table,
                **({"baseline_check": check} if horizon == "short" else {}),
            )  # fmt: skip
    save(results, args, load, start, out)
    if args.knowledge:
        print_knowledge(results, args.outdir)


def merged_results(paths):
    """The problems and horizons of several results files, as one run's `results`."""
    results = {"problems": {}}
    for path in paths:
        for problem, horizons in json.loads(pathlib.Path(path).read_text())["problems"].items():
            results["problems"].setdefault(problem, {}).update(horizons)
    return results


def print_knowledge(results, outdir):
    """`knowledge(results)`, written to `suggest_knowledge.json` and printed as `TABLE`."""
    table = knowledge(results)
    flat = {f"{cls} | {method}": entry for (cls, method), entry in table.items()}
    (pathlib.Path(outdir) / "suggest_knowledge.json").write_text(json.dumps(flat, indent=1))
    print("TABLE = {")
    for (cls, method), entry in table.items():
        print(f"    ({cls!r}, {method!r}): {entry!r},")
    print("}")


def save(results, args, load, start, out):
    results["meta"] = {
        "command": " ".join(["python", "benchmarks/work_precision.py", *sys.argv[1:]]),
        "machine": platform.processor() or platform.machine(),
        "cpu_count": os.cpu_count(),
        "cores_used": args.threads,
        "load_average_at_start": load,
        "load_average_at_end": os.getloadavg(),
        "jax": jax.__version__,
        "batch": args.batch,
        "mujoco_batch": args.mujoco_batch,
        "reference_bodies": args.reference,
        "wall_seconds": time.perf_counter() - start,
    }
    outdir = pathlib.Path(args.outdir)
    outdir.mkdir(parents=True, exist_ok=True)
    (outdir / f"{out}.json").write_text(json.dumps(results, indent=1))
    if "problems" in results:  # `--free-flow` has no plot
        plot(results, outdir / f"{out}.png")
    print(
        f"wrote {outdir / out}.json (and a plot where it has one; load average at start {load[0]:.1f})"
    )


def main_articulated(args):
    """The chains: T = 2 (pose targets) and `--long-T` (default 2·10³; energy, momentum)."""
    if args.quick:
        args.batch, args.mujoco_batch = min(args.batch, 16), min(args.mujoco_batch, 16)
        args.reference, args.long_T = min(args.reference, 2), min(args.long_T, 10.0)
        args.repeats = 1
    elif args.long_T == 2e4:
        args.long_T = 2e3
    args.reference = min(args.reference, args.batch, args.mujoco_batch)
    out = args.out or (
        "work_precision_articulated"
        + ("_step_cost" if args.step_cost_only else "_quick" if args.quick else "")
    )
    load, start = os.getloadavg(), time.perf_counter()
    results = {"problems": {}}
    for problem in args.chains:
        results["problems"][problem] = {}
        print(f"{problem}:")
        results.setdefault("step_cost", {})[problem] = chain_step_cost(problem, args)
        save(results, args, load, start, out)
        for horizon in [] if args.step_cost_only else args.horizons:
            t1 = CHAIN_T_SHORT if horizon == "short" else args.long_T
            quantities = chain_quantities(problem, horizon)
            targets = TARGETS_SHORT[:7] if horizon == "short" else TARGETS_LONG
            print(f" T = {t1:g}, batch {args.batch}, targets on {', '.join(quantities)}:")
            ref = chain_reference(problem, args.reference, t1) if horizon == "short" else None
            rows = chain_sweep(problem, horizon, t1, args, ref)
            table = chain_summary(rows, targets, quantities, horizon)
            print_summary(table)
            results["problems"][problem][horizon] = dict(
                T=t1, quantities=quantities, rows=rows, summary=table
            )
            save(results, args, load, start, out)  # after each table: a long run keeps its


if __name__ == "__main__":
    main()
