"""First calls: XLA programs compiled and wall time, each beside diffrax on the same ODE.

Each case runs in a fresh Python process (nothing compiled before, JAX's persistent
compilation cache off), lievi's call and then diffrax's on the same equations of motion,
in the order given by `--rounds` (alternated, so that a change of the machine's load
reaches both). Per call it records:

- `programs`: the XLA programs compiled (JAX's `backend_compile_duration` events);
- `first_s`: the wall time of the first call, result ready (tracing, compiling, running);
  `first_cpu_s` its CPU time (the process's, all threads: less sensitive to the load of
  a shared machine than the wall time);
- `again_programs`: the programs compiled by a second call with another `n_steps`, `h`
  and initial momentum (lievi: none; diffrax compiles per horizon);
- `run_s`: the best of 3 repeats of the first call (the run alone);
- `trace_s`, `lower_s`, `compile_s`: the first call's seconds in tracing to jaxprs, lowering
  to MLIR and XLA's compile, the sums of JAX's duration events (a trace nested in another
  counts in both; the rest of `first_s` is Python outside them, dispatch and the run).

Cases: one rigid body on SO(3) with `DEP()` (1000 steps, every step saved) against
`Tsit5`; a batch of 64 rigid bodies with `RKMK8()` (100 steps, final state) against
`Dopri8`, the batch in one state array; one free body on SE(3) with `DEP()` (100 steps,
every step saved) against `Tsit5`; a batch of 256 binary asteroids (two rigid bodies of
three point masses in mutual gravity, SE(3)², `LiePoissonSplitting()`, 100 steps, final
state), forward and the gradient of the final energy with respect to the initial momenta,
against `Tsit5` on the Newton–Euler equations with the same potential's gradient.

    python benchmarks/compile_time.py [--rounds 2] [--cases so3_dep batch64_rkmk8 ...]

Writes `benchmarks/results/compile_time.json` and prints a table.
"""

from __future__ import annotations

import argparse
import functools
import json
import os
import pathlib
import platform
import subprocess
import sys
import time


def _jit(fn):
    """`eqx.filter_jit` of a diffrax run (Python ints and strings static), as its users
    write it; imported in the child only."""

    @functools.wraps(fn)
    def call(*args, **kwargs):
        import equinox as eqx

        if not hasattr(call, "compiled"):
            call.compiled = eqx.filter_jit(fn)
        return call.compiled(*args, **kwargs)

    return call


RESULTS = pathlib.Path(__file__).resolve().parent / "results"
CASES = ("so3_dep", "batch64_rkmk8", "se3_dep", "binaries256", "binaries256_grad")


def _measure(case: str, engine: str) -> dict:
    """Runs in the child process."""
    import jax

    jax.config.update("jax_enable_x64", True)
    jax.config.update("jax_compilation_cache_dir", None)
    import jax.monitoring

    compiled = [0]
    # Seconds of the first call in each compile stage, JAX's own duration events.
    stages = dict.fromkeys(("trace_s", "lower_s", "compile_s"), 0.0)
    events = {
        "/jax/core/compile/jaxpr_trace_duration": "trace_s",
        "/jax/core/compile/jaxpr_to_mlir_module_duration": "lower_s",
        "/jax/core/compile/backend_compile_duration": "compile_s",
    }

    def listen(name, duration, **kwargs):
        if name == "/jax/core/compile/backend_compile_duration":
            compiled[0] += 1
        if name in events:
            stages[events[name]] += duration

    jax.monitoring.register_event_duration_secs_listener(listen)
    first, again = _calls(case, engine)

    def timed(call):
        compiled[0] = 0
        start, cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(call())
        return time.perf_counter() - start, compiled[0], time.process_time() - cpu

    first_s, programs, first_cpu_s = timed(first)
    split = dict(stages)
    _, again_programs, _ = timed(again)
    run_s = min(timed(first)[0] for _ in range(3))
    return dict(
        first_s=first_s,
        first_cpu_s=first_cpu_s,
        programs=programs,
        again_programs=again_programs,
        run_s=run_s,
        **split,
    )


def _calls(case: str, engine: str):
    """`(first, again)`: zero-argument calls of the case on `engine`."""
    import jax.numpy as jnp
    import numpy as np

    import lievi

    # Inputs made with NumPy: the user's own array arithmetic compiles nothing here.
    inertia = np.array([2.0, 1.0, 2 / 3])
    m_so3 = np.array([np.cos(1.1), 0.0, np.sin(1.1)])
    scale = 1 + 0.01 * np.arange(64.0)[:, None]
    eye3, eye4 = np.eye(3), np.eye(4)
    if case == "so3_dep":
        body = lievi.RigidBody(inertia)
        if engine == "lievi":
            run = lambda n, h, m: lievi.simulate(body, lievi.DEP(), eye3, m, h=h, n_steps=n)  # noqa: E731
        else:
            run = lambda n, h, m: _diffrax_so3(
                solver="Tsit5", inertia=inertia, m=m, h=h, n=n, every=True
            )  # noqa: E731
        return lambda: run(1000, 0.1, m_so3), lambda: run(700, 0.05, 1.1 * m_so3)
    if case == "batch64_rkmk8":
        body = lievi.RigidBody(inertia)
        m = m_so3 * scale
        if engine == "lievi":
            run = lambda n, h, m: lievi.simulate_batch(
                body, lievi.RKMK8(), eye3, m, h=h, n_steps=n, save=lievi.Save(every=n)
            )  # noqa: E731
        else:
            run = lambda n, h, m: _diffrax_so3(
                solver="Dopri8", inertia=inertia, m=m, h=h, n=n, every=False
            )  # noqa: E731
        return lambda: run(100, 0.1, m), lambda: run(70, 0.05, 1.1 * m)
    if case == "se3_dep":
        body = lievi.RigidBodySE3(inertia, 1.0)
        m = np.array([0.3, -0.2, 0.5, 0.1, 0.2, -0.4])
        if engine == "lievi":
            run = lambda n, h, m: lievi.simulate(body, lievi.DEP(), eye4, m, h=h, n_steps=n)  # noqa: E731
        else:
            run = lambda n, h, m: _diffrax_se3(inertia=inertia, mass=1.0, m=m, h=h, n=n)  # noqa: E731
        return lambda: run(100, 0.1, m), lambda: run(70, 0.05, 1.1 * m)
    if case.startswith("binaries256"):
        import jax

        system, g0, m0 = _binary()
        g0 = np.broadcast_to(g0, (256,) + g0.shape)
        m0 = m0 * (1 + 0.001 * np.arange(256.0))[:, None, None]
        if engine == "lievi":
            method = lievi.LiePoissonSplitting()

            def final(n, h, m):
                """`(g, m)` at the start and the end, `(256, 2, 2, …)`: the call's own
                outputs, not indexed here (eager indexing is programs of the script's)."""
                sol = lievi.simulate_batch(
                    system, method, g0, m, h=h, n_steps=n, save=lievi.Save(stats=False, every=n)
                )
                return sol.g, sol.m

            momenta = (256, 2, *m0.shape[1:])  # the momenta `final` returns
        else:

            def final(n, h, m):
                return _diffrax_binary(system=system, g0=g0, m0=m, h=h, n=n)

            momenta = m0.shape
        if case.endswith("_grad"):
            # The loss of the final momenta, `Σ m_end²`, one jitted function (the last save
            # of lievi's `(B, 2, …)`, diffrax's final state), compiled here with its
            # derivative, before the measured calls: these count the engine's programs.
            energy = jax.jit(lambda m: jnp.sum((m[:, -1] if m.ndim == 4 else m) ** 2))
            jax.block_until_ready(jax.grad(energy)(np.zeros(momenta)))

            def loss(m, n, h):
                return energy(final(n, h, m)[1])

            run = lambda n, h, m: jax.grad(loss)(m, n, h)  # noqa: E731
        else:
            run = final
        return lambda: run(100, 0.05, m0), lambda: run(70, 0.04, 1.01 * m0)
    raise ValueError(case)


def _binary():
    import jax.numpy as jnp
    import numpy as np

    import lievi

    points = jnp.array(
        [
            [[0.12, 0.0, 0.0], [-0.1, 0.08, 0.0], [0.0, -0.06, 0.09]],
            [[0.1, 0.0, 0.02], [-0.08, 0.07, 0.0], [0.0, -0.05, -0.08]],
        ]
    )
    bodies = lievi.gravitating_bodies(1.0, jnp.array([[1.0, 0.6, 0.8], [0.5, 0.4, 0.3]]), points)
    momentum = 2.4 * 1.2 / 3.6 * np.sqrt(2.4)
    g0 = np.tile(np.eye(4), (2, 1, 1))
    g0[:, 0, 3] = [-0.5, 1.0]
    m0 = np.array(
        [[0.003, 0.005, 0.01, 0.0, -momentum, 0.0], [0.004, -0.002, 0.001, 0.0, momentum, 0.0]]
    )
    return bodies, g0, m0


def _hat_products(w, x):
    """`w × x` for component-major arrays `(3, …)`."""
    import jax.numpy as jnp

    return jnp.stack(
        [w[1] * x[2] - w[2] * x[1], w[2] * x[0] - w[0] * x[2], w[0] * x[1] - w[1] * x[0]]
    )


@_jit
def _diffrax_so3(solver: str, inertia, m, h, n, every: bool):
    """The free rigid body, `Ṙ = RΩ̂`, `Π̇ = Π × Ω`, `Ω = I⁻¹Π`, with the whole batch in one
    `(12, B)` state (a batch of one for one body): diffrax's fastest formulation here."""
    import diffrax
    import jax.numpy as jnp

    m = jnp.atleast_2d(m)
    batch = m.shape[0]
    y0 = jnp.concatenate([jnp.tile(jnp.eye(3).reshape(9, 1), (1, batch)), m.T])
    inv = (1 / inertia)[:, None]

    def field(t, y, args):
        R, P = y[:9].reshape(3, 3, -1), y[9:]
        W = P * inv
        # R Ω̂: column j of R Ω̂ is R (Ω × e_j).
        hat = jnp.stack(
            [
                jnp.stack([0 * W[0], -W[2], W[1]]),
                jnp.stack([W[2], 0 * W[0], -W[0]]),
                jnp.stack([-W[1], W[0], 0 * W[0]]),
            ]
        )
        dR = jnp.einsum("ikb,kjb->ijb", R, hat)
        return jnp.concatenate([dR.reshape(9, -1), _hat_products(P, W)])

    save = diffrax.SaveAt(steps=True) if every else diffrax.SaveAt(t1=True)
    return diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        getattr(diffrax, solver)(),
        0.0,
        h * n,
        h,
        y0,
        saveat=save,
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=n,
    ).ys


@_jit
def _diffrax_se3(inertia, mass, m, h, n):
    """The free body on SE(3) in body momenta `(Π, P)`: `Ṙ = RΩ̂`, `ẋ = Rv`, `Π̇ = Π×Ω +
    P×v`, `Ṗ = P×Ω`, every step saved, `Tsit5`."""
    import diffrax
    import jax.numpy as jnp

    def field(t, y, args):
        R, P, L = y[:9].reshape(3, 3), y[12:15], y[15:]
        W, v = P / inertia, L / mass
        return jnp.concatenate(
            [
                (R @ _hat(W)).reshape(9),
                R @ v,
                jnp.cross(P, W) + jnp.cross(L, v),
                jnp.cross(L, W),
            ]
        )

    y0 = jnp.concatenate([jnp.eye(3).reshape(9), jnp.zeros(3), m])
    return diffrax.diffeqsolve(
        diffrax.ODETerm(field),
        diffrax.Tsit5(),
        0.0,
        h * n,
        h,
        y0,
        saveat=diffrax.SaveAt(steps=True),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=n,
    ).ys


def _hat(w):
    import jax.numpy as jnp

    return jnp.array([[0.0, -w[2], w[1]], [w[2], 0.0, -w[0]], [-w[1], w[0], 0.0]])


@_jit
def _diffrax_binary(system, g0, m0, h, n):
    """Two rigid bodies in mutual gravity, Newton–Euler in body momenta, the force and
    torque from the gradient of lievi's potential of the poses; the batch `vmap`-ed inside
    the vector field (one state array `(B, 2, 18)`), `Tsit5`, final state."""
    import diffrax
    import jax
    import jax.numpy as jnp

    inertia, mass = system.inertia, system.mass
    # Body-frame inverse inertia tensors, once (principal moments or full tensors).
    inverse = jnp.linalg.inv(inertia) if inertia.ndim == 3 else jax.vmap(jnp.diag)(1 / inertia)

    def pose(y):
        R, x = y[:, :9].reshape(-1, 3, 3), y[:, 9:12]
        top = jnp.concatenate([R, x[:, :, None]], axis=2)
        bottom = jnp.broadcast_to(jnp.array([0.0, 0.0, 0.0, 1.0]), (R.shape[0], 1, 4))
        return jnp.concatenate([top, bottom], axis=1)

    def one(y):
        R, P, L = y[:, :9].reshape(-1, 3, 3), y[:, 12:15], y[:, 15:]
        dV = jax.grad(system.potential_energy)(pose(y))
        GR, force = dV[:, :3, :3], -dV[:, :3, 3]
        M = jnp.einsum("bki,bkj->bij", GR, R) - jnp.einsum("bki,bkj->bij", R, GR)
        torque = jnp.stack([M[:, 2, 1], M[:, 0, 2], M[:, 1, 0]], axis=-1)
        W, v = jnp.einsum("bij,bj->bi", inverse, P), L / mass[:, None]
        dR = jnp.einsum("bik,bkj->bij", R, jax.vmap(_hat)(W))
        return jnp.concatenate(
            [
                dR.reshape(-1, 9),
                jnp.einsum("bij,bj->bi", R, v),
                jnp.cross(P, W) + jnp.cross(L, v) + torque,
                jnp.cross(L, W) + jnp.einsum("bji,bj->bi", R, force),
            ],
            axis=1,
        )

    y0 = jnp.concatenate([g0[:, :, :3, :3].reshape(*g0.shape[:2], 9), g0[:, :, :3, 3], m0], axis=-1)
    ys = diffrax.diffeqsolve(
        diffrax.ODETerm(lambda t, y, args: jax.vmap(one)(y)),
        diffrax.Tsit5(),
        0.0,
        h * n,
        h,
        y0,
        saveat=diffrax.SaveAt(t1=True),
        stepsize_controller=diffrax.ConstantStepSize(),
        max_steps=n,
    ).ys[-1]
    return ys[..., :12], ys[..., 12:]


def _child(case: str, engine: str) -> dict:
    out = subprocess.run(
        [sys.executable, __file__, "--child", case, engine],
        capture_output=True,
        text=True,
        check=True,
        env=dict(
            os.environ,
            JAX_PLATFORMS=os.environ.get("JAX_PLATFORMS", "cpu"),
            # The lievi of this checkout (a script's own folder, not the working directory,
            # is on its path: an installed lievi would be measured instead).
            PYTHONPATH=os.pathsep.join(
                [str(pathlib.Path(__file__).resolve().parents[1]), os.environ.get("PYTHONPATH", "")]
            ),
        ),
    )
    return json.loads(out.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--cases", nargs="*", default=list(CASES))
    parser.add_argument("--rounds", type=int, default=2)
    parser.add_argument("--out", default="compile_time")
    parser.add_argument("--child", nargs=2, help=argparse.SUPPRESS)
    options = parser.parse_args()
    if options.child:
        print(json.dumps(_measure(*options.child)))
        return
    rows = []
    for case in options.cases:
        runs = {"lievi": [], "diffrax": []}
        for index in range(options.rounds):
            order = ("lievi", "diffrax") if index % 2 == 0 else ("diffrax", "lievi")
            for engine in order:
                runs[engine].append(_child(case, engine))
        row = {"case": case}
        for engine, measured in runs.items():
            row[engine] = {
                "programs": measured[0]["programs"],
                "again_programs": measured[0]["again_programs"],
                "first_s": [m["first_s"] for m in measured],
                "first_cpu_s": [m["first_cpu_s"] for m in measured],
                "run_s": min(m["run_s"] for m in measured),
                **{k: [m[k] for m in measured] for k in ("trace_s", "lower_s", "compile_s")},
            }
        ratio = [a["first_s"] / b["first_s"] for a, b in zip(runs["lievi"], runs["diffrax"])]
        row["first_call_ratio"] = ratio
        cpu = [a["first_cpu_s"] / b["first_cpu_s"] for a, b in zip(runs["lievi"], runs["diffrax"])]
        row["first_call_cpu_ratio"] = cpu
        rows.append(row)
        lv, dx = row["lievi"], row["diffrax"]
        print(
            f"{case:18s} lievi {lv['programs']:2d} programs (+{lv['again_programs']}), first "
            f"{min(lv['first_s']):6.2f} s | diffrax {dx['programs']:2d} (+{dx['again_programs']}),"
            f" first {min(dx['first_s']):6.2f} s | first-call ratio "
            f"{', '.join(f'{r:.2f}' for r in ratio)} (CPU time {', '.join(f'{r:.2f}' for r in cpu)})",
            flush=True,
        )
        for engine in ("lievi", "diffrax"):
            e = row[engine]
            print(
                f"{'':18s} {engine:7s} first call: trace {min(e['trace_s']):5.2f} s, lowering "
                f"{min(e['lower_s']):5.2f} s, XLA {min(e['compile_s']):5.2f} s",
                flush=True,
            )
    meta = {
        "machine": platform.processor() or platform.machine(),
        "cpus": os.cpu_count(),
        "load_before_after": os.getloadavg(),
        "python": platform.python_version(),
    }
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / f"{options.out}.json"
    path.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
