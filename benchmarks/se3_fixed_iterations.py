"""How many free SE(3) bodies the DEP kernel's fixed Newton iterations leave to its loop.

Every body of a batch takes the kernel's fixed iterations (a chord step and two Newton
steps, `lievi/_kernels/_se3.py`); a body they leave above the tolerance continues in the
gathered Newton loop. This counts the bodies that would: `simulate_batch` with
`DEP(max_steps=3)` (no loop, so such a body is reported failed), for random free bodies
(principal moments 0.5–2, masses 0.5–3, `|ω| ≤ 0.3`, speeds up to 3; seed 0), over a
few steps of each size, with both charts.

    python benchmarks/se3_fixed_iterations.py [--bodies 20000] [--steps 5] [--h 0.05 0.1 0.2]
                                              [--out se3_fixed_iterations]

Writes `benchmarks/results/<out>.json` (with the path of the `lievi` imported: run it
with `PYTHONPATH=<other tree>` to count for another checkout).
"""

from __future__ import annotations

import argparse
import json
import pathlib

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"


def bodies(count: int, seed: int = 0):
    rng = np.random.default_rng(seed)
    inertia, mass = rng.uniform(0.5, 2.0, (count, 3)), rng.uniform(0.5, 3.0, count)
    w = rng.normal(size=(count, 3))
    w *= (rng.uniform(0.0, 0.3, count) / np.linalg.norm(w, axis=1))[:, None]
    v = rng.normal(size=(count, 3)) * rng.uniform(0.0, 3.0, (count, 1))
    m0 = np.concatenate([inertia * w, mass[:, None] * v], axis=1)
    system = jax.vmap(lievi.RigidBodySE3)(jnp.asarray(inertia), jnp.asarray(mass))
    return system, jnp.broadcast_to(jnp.eye(4), (count, 4, 4)), jnp.asarray(m0)


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--bodies", type=int, default=20_000)
    parser.add_argument("--steps", type=int, default=5)
    parser.add_argument("--h", type=float, nargs="+", default=[0.05, 0.1, 0.2])
    parser.add_argument("--out", default="se3_fixed_iterations")
    args = parser.parse_args()
    print(f"lievi from {lievi.__file__}")
    system, g0, m0 = bodies(args.bodies)
    rows = []
    for chart in ("exp", "cayley"):
        for h in args.h:
            sol = lievi.simulate_batch(
                system,
                lievi.DEP(chart=chart, max_steps=3),
                g0,
                m0,
                h=h,
                n_steps=args.steps,
                system_axis=0,
                throw=False,
            )
            left = int(np.sum(np.asarray(sol.result) != int(lievi.RESULTS.successful)))
            rows.append({"chart": chart, "h": h, "bodies_needing_the_loop": left})
            print(f"{chart:7s} h = {h:5.3f}: {left} of {args.bodies} bodies need the loop")
    document = {
        "description": __doc__.splitlines()[0],
        "bodies": args.bodies,
        "steps": args.steps,
        "lievi": lievi.__file__,
        "rows": rows,
    }
    path = RESULTS / f"{args.out}.json"
    path.write_text(json.dumps(document, indent=2) + "\n")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
