"""The demo's figures (matplotlib, imported only when a figure is drawn, so the package
itself does not need it)."""

from __future__ import annotations

from typing import Any

import numpy as np

from .problems import CONTROL_AXIS, CONTROL_T, CONTROL_THETA, SPACECRAFT_INERTIA


def _pyplot():
    try:
        import matplotlib
    except ImportError:
        raise SystemExit(
            "--plot needs matplotlib: pip install matplotlib (or lievi[plot])."
        ) from None
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _flat(m):
    """Momenta `(T, …)` as `(T, k)`: one row per saved time."""
    m = np.asarray(m)
    return m.reshape(m.shape[0], -1)


def save_plot(
    path: str,
    ts,
    m_ref,
    energy_ref,
    runs: list[tuple[str, Any, Any]],
    title: str = "Hairer–Lubich–Wanner rigid body, I = (2, 1, 2/3)",
) -> None:
    """Left: Π components against t (reference in grey); right: |E − E₀| against t.

    `runs`: `(name, Solution, energy trajectory)` per integrator. matplotlib is imported
    here, so the package itself does not need it.
    """
    plt = _pyplot()

    ts = np.asarray(ts)
    energy0 = float(energy_ref[0])
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    styles = ("--", ":", "-.", (0, (5, 1)), (0, (3, 1, 1, 1)))

    fig = plt.figure(figsize=(13, 6.5), layout="constrained")
    grid = fig.add_gridspec(3, 2)
    axes = []
    for i in range(3):
        ax = fig.add_subplot(grid[i, 0], sharex=axes[0] if axes else None)
        axes.append(ax)
        # The first three momentum coordinates: Π, or the first body's Π for several bodies.
        ax.plot(ts, _flat(m_ref)[:, i], color="black", lw=3, alpha=0.3, label="reference (DOP853)")
        for j, (name, solution, _) in enumerate(runs):
            ax.plot(
                ts,
                _flat(solution.m)[:, i],
                color=colours[j % len(colours)],
                ls=styles[j % len(styles)],
                lw=1.2,
                label=name,
            )
        ax.set_ylabel(f"$\\Pi_{i + 1}$")
        ax.grid(True, alpha=0.3)
        if i < 2:
            ax.tick_params(labelbottom=False)
    axes[0].set_title("body momentum Π(t)")
    low, high = axes[0].get_ylim()
    axes[0].set_ylim(low, high + 0.35 * (high - low))  # room for the legend
    axes[0].legend(fontsize="small", loc="upper right", ncol=min(3, len(runs) + 1))
    axes[-1].set_xlabel("t")

    def positive(x):  # log axes: drop exact zeros (t = 0)
        x = np.abs(np.asarray(x) - energy0)
        return np.where(x > 0, x, np.nan)

    ax = fig.add_subplot(grid[:, 1])
    for j, (name, _, energy) in enumerate(runs):
        ax.semilogy(ts, positive(energy), color=colours[j % len(colours)], lw=1.0, label=name)
    ax.semilogy(
        ts, positive(energy_ref), color="black", alpha=0.3, lw=1.0, label="reference (DOP853)"
    )
    ax.set_title(f"energy error |E − E₀|  (E₀ = {energy0:.6g})")
    ax.set_xlabel("t")
    ax.set_ylabel("|E − E₀|")
    ax.grid(True, which="major", alpha=0.3)
    ax.legend(fontsize="small", loc="lower right")

    h = ts[1] - ts[0] if len(ts) > 1 else float("nan")
    fig.suptitle(f"lievi: {title}, h = {h:g}, T = {ts[-1]:g}")
    fig.savefig(path, dpi=110)
    plt.close(fig)


def save_control_plot(path, sphere_n, sphere_u, craft_u) -> None:
    """Left: the sphere's discrete optimum against the closed form; right: the
    spacecraft's torques."""
    plt = _pyplot()

    fig, (left, right) = plt.subplots(1, 2, figsize=(12, 4.5), layout="constrained")
    for ax, u, title in (
        (left, sphere_u, f"spherical body, N = {sphere_n}: u·a against the closed form"),
        (right, craft_u, f"spacecraft I = {SPACECRAFT_INERTIA}, N = {len(craft_u)}: torques"),
    ):
        n = len(u)
        edges = np.linspace(0, CONTROL_T, n + 1)
        if u is sphere_u:
            t = np.linspace(0, CONTROL_T, 400)
            ax.plot(
                t,
                CONTROL_THETA / CONTROL_T**2 * (6 - 12 * t / CONTROL_T),
                "k",
                lw=3,
                alpha=0.3,
                label="closed form",
            )
            ax.stairs(
                np.asarray(u @ CONTROL_AXIS), edges, baseline=None, label="discrete optimum u·a"
            )
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
