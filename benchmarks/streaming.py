"""A streamed run larger than memory: `lievi.stream_batch` to `.npy` files, peak memory.

Random free rigid bodies (inertia and momentum per body, all from the identity), `DEP`
(exp chart, the fast path), step 0.01, every `--save-every`-th step of `(g, m)` written by
`lievi.NpyWriter` in chunks of `--chunk` bodies and segments of `--segment` steps.
Reports the wall time, body-steps per second, the bytes written, the peak resident memory
of the process (`resource.getrusage`, which counts everything the process held: JAX's
runtime, the inputs, one chunk's segment) against the size of the output, and checks
`--check` bodies spread over the batch against one in-memory `simulate_batch` call on
them (the largest difference of the written `g`, `m`). The output is deleted afterwards
(unless `--keep`).

    python benchmarks/streaming.py [--bodies 1000000] [--steps 10000] [--save-every 25]
                                   [--chunk 10000] [--segment 1000] [--dir /tmp/...]

The full configuration (10⁶ bodies × 10⁴ steps, every 25th step: 4.8e9 numbers, 38 GB
in float64) needs that much free disk; the script refuses to start without it. Writes
`benchmarks/results/streaming_<bodies>x<steps>.json`.
"""

from __future__ import annotations

import argparse
import json
import pathlib
import resource
import shutil
import subprocess
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lievi  # noqa: E402

RESULTS = pathlib.Path(__file__).resolve().parent / "results"
H = 0.01


def problem(bodies: int):
    rng = np.random.default_rng(0)
    inertia = rng.uniform(0.5, 2.0, (bodies, 3))
    m0 = rng.normal(size=(bodies, 3))
    return inertia, m0


def peak_rss_bytes() -> int:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss * 1024  # KiB on Linux


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--bodies", type=int, default=1_000_000)
    parser.add_argument("--steps", type=int, default=10_000)
    parser.add_argument("--save-every", type=int, default=25)
    parser.add_argument("--chunk", type=int, default=10_000)
    parser.add_argument("--segment", type=int, default=1000)
    parser.add_argument("--check", type=int, default=64, help="bodies checked in memory")
    parser.add_argument("--dir", default="/tmp/lievi-streaming")
    parser.add_argument("--keep", action="store_true", help="keep the written output")
    args = parser.parse_args()

    directory = pathlib.Path(args.dir)
    if directory.exists():
        raise SystemExit(f"{directory} exists; pass a new --dir (or delete it).")
    saves = args.steps // args.save_every + 1
    expected = args.bodies * saves * (9 + 3) * 8
    free = shutil.disk_usage(directory.parent).free
    print(f"output {expected / 1e9:.2f} GB, free on {directory.parent}: {free / 1e9:.1f} GB")
    if expected > 0.9 * free:
        raise SystemExit("not enough free disk for the output; lower --bodies or --steps.")

    inertia, m0 = problem(args.bodies)
    bodies = jax.vmap(lievi.RigidBody)(jnp.asarray(inertia))
    rss_before = peak_rss_bytes()
    started = time.perf_counter()
    lievi.stream_batch(
        bodies,
        lievi.DEP(),
        np.eye(3),
        m0,
        h=H,
        n_steps=args.steps,
        save=lievi.Save(every=args.save_every),
        writer=lievi.NpyWriter(directory),
        chunk_size=args.chunk,
        segment_steps=args.segment,
        progress_meter=lievi.TextProgressMeter(prefix="streaming"),
    )
    seconds = time.perf_counter() - started
    peak = peak_rss_bytes()
    written = sum(p.stat().st_size for p in directory.rglob("*") if p.is_file())
    allocated = sum(p.stat().st_blocks * 512 for p in directory.rglob("*") if p.is_file())

    # A subset spread over the batch (first and last body included) against memory.
    rows = np.unique(np.linspace(0, args.bodies - 1, args.check).astype(int))
    reference = lievi.simulate_batch(
        jax.vmap(lievi.RigidBody)(jnp.asarray(inertia[rows])),
        lievi.DEP(),
        np.eye(3),
        m0[rows],
        h=H,
        n_steps=args.steps,
        save=lievi.Save(stats=False, every=args.save_every),
    )
    g = np.load(directory / "g.npy", mmap_mode="r")[rows]
    m = np.load(directory / "m.npy", mmap_mode="r")[rows]
    result = np.load(directory / "result.npy", mmap_mode="r")
    diff_g = float(np.max(np.abs(g - np.asarray(reference.g))))
    diff_m = float(np.max(np.abs(m - np.asarray(reference.m))))
    failed = int(np.sum(result != lievi.RESULTS.successful))
    if not args.keep:
        shutil.rmtree(directory)

    load = subprocess.run(["uptime"], capture_output=True, text=True).stdout.strip()
    report = {
        "bodies": args.bodies,
        "steps": args.steps,
        "save_every": args.save_every,
        "chunk": args.chunk,
        "segment": args.segment,
        "seconds": seconds,
        "body_steps_per_second": args.bodies * args.steps / seconds,
        "bytes_written": written,
        "bytes_allocated_on_disk": allocated,
        "peak_rss_bytes": peak,
        "peak_rss_before_run_bytes": rss_before,
        "peak_rss_over_output": peak / written,
        "checked_bodies": int(len(rows)),
        "max_abs_diff_g": diff_g,
        "max_abs_diff_m": diff_m,
        "failed_bodies": failed,
        "device": str(jax.devices()[0]),
        "uptime": load,
        "output_deleted": not args.keep,
    }
    print(json.dumps(report, indent=2))
    RESULTS.mkdir(exist_ok=True)
    out = RESULTS / f"streaming_{args.bodies}x{args.steps}.json"
    out.write_text(json.dumps(report, indent=2) + "\n")
    print(f"wrote {out}")
    assert diff_g <= 1e-12 and diff_m <= 1e-12, (diff_g, diff_m)


if __name__ == "__main__":
    main()
