"""Work–precision of coupled rigid bodies at a long horizon (`work_precision.py --coupled`).

Two chaotic systems of rigid bodies on SE(3)ᴺ, where no trajectory can be a target at a
long horizon and only the invariants can:

- **binary**: the binary asteroid of `lievi/_cli/problems.py` (two bodies of three point
  masses, G = 1, `lievi.gravitating_bodies`; orbit period ≈ 8), each system with its own
  spins (the base body angular momenta times `1 + 0.05·noise`; the linear momenta as
  given, so the total linear momentum is zero); `--batch` systems (256), T = `--long-T`
  (2·10⁴, about 2,400 orbits).
- **water**: `--molecules` (64) rigid water-like molecules of
  `benchmarks/rigid_molecules_jaxmd.py` (`lievi_molecules`: LJ between O sites and
  Coulomb between all sites of different molecules, free space, no cut-off), one system
  per seed (`--water-batch`, 1); T = `--water-T` (2000: 10⁵ steps at h = 0.02, the
  largest step of the sweep, where the compositions' energy errors are useful).

Errors, each the largest over the systems and over `SAMPLES` (100) evenly spaced times:
the relative energy error `|E − E₀| / |E₀|`, and the change of the total angular and
linear momentum, each over a scale of the bodies' own momenta at t = 0 (the totals can
be near zero): `Σᵢ |RᵢΠᵢ + (xᵢ − x̄) × pᵢ|` and `Σᵢ |pᵢ|`. A run meets a target when all
three are below it. Cost: CPU seconds per system (the batch's best CPU time of
`--repeats` compiled calls over the batch), one core.

Methods: lievi's `LiePoissonSplitting()` and its compositions (structure-preserving),
`DEP(chart="cayley")`, and the non-geometric `RKMK4`; `simulate_batch` over the batch
of systems (`simulate` for a batch of one). diffrax (`Dopri8`, `Tsit5`, constant steps
and PID at rtol = atol = tol): the Newton–Euler equations of all bodies of all systems
in ONE state array `(B, N, 18)` (per body x, p world, R row-major, Π body), written here
(`newton_euler_field`): ẋ = p/m, ṗ = −∂V/∂x, Ṙ = RΩ̂, Π̇ = Π × J⁻¹Π + τ, with the force
and the body torque `τ_a = −∂/∂ε_a V(R(I + ε̂), x)|₀` from lievi's potential energy by
`jax.grad` (physics, not integrator). `check_field` tests this field: invariants to
~1e-12 over a short run at a tiny tolerance, and the final state against lievi's
`RKMK8` at T = 2.

    python benchmarks/work_precision.py --coupled binary --batch 16   # 10 min (256: hours)
    python benchmarks/work_precision.py --coupled water               # ~1 h at T = 2000
    python benchmarks/work_precision.py --coupled binary water --quick
    python benchmarks/work_precision.py --coupled binary --check    # the field check only
"""

from __future__ import annotations

import os
import time
from functools import partial

import jax
import jax.numpy as jnp
import numpy as np
from work_precision import (
    TARGETS_LONG,
    best_cpu_seconds,
    print_summary,
    sample_every,
    save,
    step_control,
    summary,
)

import lievi

SAMPLES = 100  # saved states per run; every run's step count is a multiple
QUANTITIES = ("energy", "angular momentum", "linear momentum")

# name: (integrator, order, structure-preserving)
COUPLED_METHODS = {
    "splitting": (lambda: lievi.LiePoissonSplitting(), 2, True),
    "splitting ∘ 4": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), order=4), 4, True),
    "splitting ∘ 6 SS": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), 6, "sofroniou-spaletta"), 6, True),
    "splitting ∘ 8 SS": (lambda: lievi.Composition(lievi.LiePoissonSplitting(), 8, "sofroniou-spaletta"), 8, True),
    "DEP Cayley": (lambda: lievi.DEP(chart="cayley"), 2, True),
    "RKMK4": (lambda: lievi.RKMK4(), 4, False),
}  # fmt: skip
DIFFRAX_SOLVERS = {"Dopri8": 8, "Tsit5": 5}


# ---- the problems -------------------------------------------------------------------------


def binary_states(batch, seed=0):
    """`(system, g0 (B, 2, 4, 4), m0 (B, 2, 6))`: the problem's spins perturbed."""
    from lievi._cli.problems import binary_problem

    system, g0, m0 = binary_problem()
    noise = np.random.default_rng(seed).normal(size=(batch, 2, 3))
    m = np.broadcast_to(np.asarray(m0), (batch, 2, 6)).copy()
    m[..., :3] *= 1 + 0.05 * noise
    return system, np.broadcast_to(np.asarray(g0), (batch, 2, 4, 4)).copy(), m


def water_states(batch, molecules):
    """One system of `molecules` molecules per seed `0 … batch − 1` (the same sites)."""
    from rigid_molecules_jaxmd import lievi_molecules

    states = [lievi_molecules(molecules, seed=s)[1:3] for s in range(batch)]
    system = lievi_molecules(molecules)[0]
    return (
        system,
        np.stack([np.asarray(g) for g, _ in states]),
        np.stack([np.asarray(m) for _, m in states]),
    )


def problem_states(problem, args):
    if problem == "binary":
        return binary_states(args.batch)
    return water_states(args.water_batch, args.molecules)


def steps_for(problem, order, quick):
    """Step sizes (each `T/h` a multiple of `SAMPLES`): from a step where the error is
    useful (at most ~1e-2) down to one near round-off, per order."""
    if problem == "binary":
        if quick:
            return [0.05, 0.025]
        by_order = {2: [0.05, 0.025, 0.0125], 4: [0.2, 0.1, 0.05, 0.025]}
        return by_order.get(order, [0.4, 0.2, 0.1, 0.05])
    if quick:
        return [0.01]
    return [0.02, 0.01] if order >= 4 else [0.01, 0.005]


def tolerances_for(quick):
    return [1e-6, 1e-10] if quick else [1e-6, 1e-8, 1e-10, 1e-12]


# ---- errors -------------------------------------------------------------------------------


def momentum_scales(g, m):
    """Per system `(Σᵢ |RᵢΠᵢ + (xᵢ − x̄) × pᵢ|, Σᵢ |pᵢ|)` of a state `g (B, N, 4, 4)`,
    `m (B, N, 6)`: the bodies' own momenta, the scale of the totals' errors."""
    R, x = g[..., :3, :3], g[..., :3, 3]
    p = np.einsum("...ij,...j->...i", R, m[..., 3:])
    centre = x.mean(axis=-2, keepdims=True)
    each = np.einsum("...ij,...j->...i", R, m[..., :3]) + np.cross(x - centre, p)
    return np.linalg.norm(each, axis=-1).sum(-1), np.linalg.norm(p, axis=-1).sum(-1)


def errors(system, g0, m0, g, m):
    """`g (B, K, N, 4, 4)`, `m (B, K, N, 6)` at the saved times; each error the largest
    over the systems and the times (NaN if any state is not finite)."""
    g, m = np.asarray(g), np.asarray(m)
    if not (np.all(np.isfinite(g)) and np.all(np.isfinite(m))):
        return dict.fromkeys(QUANTITIES, float("nan"))
    energy = jax.jit(jax.vmap(jax.vmap(partial(lievi.diagnostics.energy, system))))
    total = jax.jit(jax.vmap(jax.vmap(partial(lievi.diagnostics.total_momentum, system))))
    E, E0 = np.asarray(energy(g, m)), np.asarray(energy(g0[:, None], m0[:, None]))
    L, L0 = np.asarray(total(g, m)), np.asarray(total(g0[:, None], m0[:, None]))
    angular, linear = momentum_scales(g0, m0)
    change = np.abs(L - L0)
    out = {
        "energy": np.abs(E - E0) / np.abs(E0),
        "angular momentum": np.linalg.norm(change[..., :3], axis=-1) / angular[:, None],
        "linear momentum": np.linalg.norm(change[..., 3:], axis=-1) / linear[:, None],
    }
    return {k: float(np.max(v)) for k, v in out.items()}


# ---- lievi --------------------------------------------------------------------------------


def lievi_run(states, integrator, h, t1, repeats):
    """`simulate_batch` over the systems' initial states (`simulate` for one system)."""
    system, g0, m0 = states
    n = int(round(t1 / h))
    save_ = lievi.Save(g=True, m=True, stats=False, every=sample_every(n, SAMPLES))

    @jax.jit
    def run(g0, m0):
        if g0.shape[0] == 1:
            sol = lievi.simulate(system, integrator, g0[0], m0[0], h=h, n_steps=n,
                                 throw=False, save=save_)  # fmt: skip
            return sol.g[None, 1:], sol.m[None, 1:], sol.result[None]
        sol = lievi.simulate_batch(system, integrator, g0, m0, h=h, n_steps=n,
                                   throw=False, save=save_)  # fmt: skip
        return sol.g[:, 1:], sol.m[:, 1:], sol.result

    (g, m, result), seconds = best_cpu_seconds(run, (jnp.asarray(g0), jnp.asarray(m0)), repeats)
    return g, m, seconds, bool(np.all(np.asarray(result) == 0))


# ---- diffrax: the Newton–Euler equations, all systems in one state --------------------------


def to_state(g, m):
    """`(…, N, 4, 4)`, `(…, N, 6)` → `(…, N, 18)`: x, p = RP, R row-major, Π."""
    R, x = g[..., :3, :3], g[..., :3, 3]
    p = jnp.einsum("...ij,...j->...i", R, m[..., 3:])
    return jnp.concatenate([x, p, R.reshape(*R.shape[:-2], 9), m[..., :3]], axis=-1)


def unpack(y):
    """`(x, p, R, Π)` of a state `(…, N, 18)`."""
    return y[..., :3], y[..., 3:6], y[..., 6:15].reshape(*y.shape[:-1], 3, 3), y[..., 15:]


def from_state(y):
    """The inverse of `to_state`."""
    x, p, R, Pi = unpack(y)
    P = jnp.einsum("...ji,...j->...i", R, p)
    g = jnp.zeros((*y.shape[:-1], 4, 4), y.dtype)
    g = g.at[..., :3, :3].set(R).at[..., :3, 3].set(x).at[..., 3, 3].set(1.0)
    return g, jnp.concatenate([Pi, P], axis=-1)


def hat(v):
    zero = jnp.zeros_like(v[..., 0])
    return jnp.stack(
        [jnp.stack([zero, -v[..., 2], v[..., 1]], -1),
         jnp.stack([v[..., 2], zero, -v[..., 0]], -1),
         jnp.stack([-v[..., 1], v[..., 0], zero], -1)], -2,
    )  # fmt: skip


def newton_euler_field(system):
    """The field on `y (B, N, 18)`: every body of every system, one array. The force and
    the body torque are the gradients of the potential energy (lievi's, of one system's
    poses) in the positions and in a body-frame rotation `R → R(I + ε̂)` at ε = 0."""
    inverse = jnp.linalg.inv(system.tensor[:, :3, :3])  # (N, 3, 3)
    mass = jnp.asarray(system.mass)[:, None]

    def potential(x, eps, R):  # one system: (N, 3), (N, 3), (N, 3, 3)
        turned = R + R @ hat(eps)
        g = jnp.zeros((x.shape[0], 4, 4), x.dtype)
        g = g.at[:, :3, :3].set(turned).at[:, :3, 3].set(x).at[:, 3, 3].set(1.0)
        return system.potential_energy(g)

    gradient = jax.vmap(jax.grad(potential, argnums=(0, 1)))

    def field(t, y, args):
        x, p, R, Pi = unpack(y)
        dVdx, dVde = gradient(x, jnp.zeros_like(x), R)
        omega = jnp.einsum("nij,bnj->bni", inverse, Pi)
        dR = jnp.cross(R, omega[..., None, :])  # row i of R crossed with ω: RΩ̂
        dPi = jnp.cross(Pi, omega) - dVde
        return jnp.concatenate([p / mass, -dVdx, dR.reshape(*y.shape[:-1], 9), dPi], axis=-1)

    return field


def diffrax_run(states, solver, knob, adaptive, t1, repeats, samples=SAMPLES):
    import diffrax

    system, g0, m0 = states
    y0 = to_state(jnp.asarray(g0), jnp.asarray(m0))
    ts = jnp.linspace(0.0, t1, samples + 1)[1:]
    control, max_steps = step_control(knob, adaptive, t1)
    term = diffrax.ODETerm(newton_euler_field(system))

    @jax.jit
    def run(y0):
        sol = diffrax.diffeqsolve(
            term, getattr(diffrax, solver)(), t0=0.0, t1=t1, y0=y0,
            saveat=diffrax.SaveAt(ts=ts), max_steps=max_steps,
            adjoint=diffrax.ForwardMode(), throw=False, **control,
        )  # fmt: skip
        return sol.ys, sol.result == diffrax.RESULTS.successful

    (ys, ok), seconds = best_cpu_seconds(run, (y0,), repeats)
    g, m = from_state(jnp.moveaxis(ys, 0, 1))  # (B, K, N, …)
    return g, m, seconds, bool(ok)


def check_field(problem, states, t1=2.0):
    """The diffrax field against lievi: the invariants over a short run at a tiny
    tolerance, and the final state against `RKMK8` at a small step, at `t1`."""
    system, g0, m0 = states
    g0, m0 = g0[:2], m0[:2]
    g, m, _, ok = diffrax_run((system, g0, m0), "Dopri8", 1e-14, True, t1, 1, samples=4)
    invariants = errors(system, g0, m0, g, m)
    n = 400 * 4
    gk, mk, _, ok_k = lievi_run((system, g0, m0), lievi.RKMK8(), t1 / n, t1, 1)
    apart = max(
        float(np.max(np.abs(np.asarray(g)[:, -1] - np.asarray(gk)[:, -1]))),
        float(np.max(np.abs(np.asarray(m)[:, -1] - np.asarray(mk)[:, -1])) / np.max(np.abs(m0))),
    )
    out = dict(T=t1, invariants_dopri8_tol_1e_14=invariants, final_vs_rkmk8=apart, ok=ok and ok_k)
    print(f"  field check ({problem}, T = {t1:g}): Dopri8 tol 1e-14 invariants "
          + ", ".join(f"{k} {v:.1e}" for k, v in invariants.items())
          + f"; final state vs lievi RKMK8 (h = {t1 / n:g}) {apart:.1e}", flush=True)  # fmt: skip
    return out


# ---- the sweep ----------------------------------------------------------------------------


def sweep(problem, states, t1, args, meets_all, saved=lambda rows: None):
    """Every run's cost (CPU seconds per system) and errors; a sequence's runs after one
    that costs at least the family's cheapest run meeting every target are skipped.
    `saved(rows)` after each run: a long sweep stopped early keeps its runs."""
    rows, systems = [], states[1].shape[0]
    g0, m0 = states[1], states[2]

    def record(family, method, knob, run, structure=False):
        start = time.perf_counter()
        try:
            g, m, seconds, ok = run()
        except Exception as error:  # a method this system does not support
            print(f"  {method:<26} {knob:>8.3g}  skipped: {type(error).__name__}: {error}"[:160])
            return None
        errs = errors(states[0], g0, m0, g, m) if ok else dict.fromkeys(QUANTITIES, float("nan"))
        rows.append(dict(family=family, method=method, knob=knob, cost=seconds / systems,
                         ok=ok, structure_preserving=structure, **errs))  # fmt: skip
        shown = "  ".join(f"{q} {errs[q]:8.1e}" for q in QUANTITIES)
        print(f"  {method:<26} {knob:>8.3g}  {seconds / systems:9.3g} s/system  {shown}"
              f"  ({time.perf_counter() - start:.0f} s wall)", flush=True)  # fmt: skip
        saved(rows)
        return rows[-1]

    def dominated(family, previous):
        """The next run of a sequence costs more than `previous`: left out when `previous`
        already costs as much as the family's cheapest run meeting every target (it may be
        that run), since it could then be the family's cheapest at no target."""
        bound = min(
            (r["cost"] for r in rows if r["family"] == family and meets_all(r)), default=np.inf
        )
        if previous is None or previous["cost"] < bound:
            return False
        print(f"  the rest skipped: dominated ({previous['cost']:.3g} ≥ {bound:.3g})")
        return True

    for method, (make, order, structure) in COUPLED_METHODS.items():
        if method not in (args.coupled_methods or COUPLED_METHODS):
            continue
        previous = None
        for h in steps_for(problem, order, args.quick):
            if dominated("lievi", previous):
                break
            run = partial(lievi_run, states, make(), h, t1, args.repeats)
            previous = record("lievi", f"lievi {method}", h, run, structure) or previous
    try:
        import diffrax  # noqa: F401
    except ImportError:
        print("  diffrax not installed: skipped")
        return rows
    for solver, order in DIFFRAX_SOLVERS.items():  # Dopri8 first: it bounds Tsit5
        for adaptive, knobs in (
            (False, steps_for(problem, order, args.quick)),
            (True, tolerances_for(args.quick)),
        ):
            name, previous = f"diffrax {solver} {'PID' if adaptive else 'constant'}", None
            for knob in knobs:
                if dominated("diffrax", previous):
                    break
                run = partial(diffrax_run, states, solver, knob, adaptive, t1, args.repeats)
                previous = record("diffrax", name, knob, run) or previous
    return rows


def meets(target, row):
    return row["ok"] and all(row[q] <= target for q in QUANTITIES)


def main(args):
    """`--coupled binary water`: one table per problem at its long horizon."""
    if args.quick:
        args.batch, args.water_batch = min(args.batch, 16), 1
        args.long_T, args.water_T, args.repeats = min(args.long_T, 200.0), 20.0, 1
        args.molecules = min(args.molecules, 8)
    load, start = os.getloadavg(), time.perf_counter()
    results = {"problems": {}}
    for problem in args.coupled:
        states = problem_states(problem, args)
        t1 = args.long_T if problem == "binary" else args.water_T
        systems = states[1].shape[0]
        size = f"{systems} systems" + (
            f" of {args.molecules} molecules" if problem == "water" else ""
        )
        print(f"{problem}: T = {t1:g}, {size}, targets on {', '.join(QUANTITIES)}:")
        check = check_field(problem, states)
        if args.check:
            results["problems"][problem] = dict(field_check=check)
            continue
        out = args.out or f"work_precision_{problem}_long" + ("_quick" if args.quick else "")

        def saved(rows, problem=problem, t1=t1, systems=systems, check=check, out=out):
            table = summary(rows, TARGETS_LONG, QUANTITIES)
            results["problems"][problem] = {
                "long": dict(T=t1, systems=systems, quantities=QUANTITIES, rows=rows,
                             summary=table, field_check=check, cost_unit="CPU seconds per system",
                             **({"molecules": args.molecules} if problem == "water" else {}))
            }  # fmt: skip
            save({"problems": {problem: results["problems"][problem]}}, args, load, start, out)
            return table

        rows = sweep(problem, states, t1, args, partial(meets, min(TARGETS_LONG)), saved)
        print_summary(saved(rows))
    return results
