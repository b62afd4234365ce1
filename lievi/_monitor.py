"""Invariant monitors: a run that lets an invariant drift past a tolerance is reported.

A fixed-step run cannot know that it went wrong: a near-collision of two bodies at too
large a step can give a finite, "successful" trajectory whose energy is off by many times
its size. A monitor checks one invariant of each body at every save against its initial
value and, past the tolerance, ends the body's run with `RESULTS.invariant_drift` (its
state saved as NaN from that save on, as after any failure). Off by default: it costs one
evaluation of the invariant per save.
"""

from __future__ import annotations

import abc

import equinox as eqx
import jax.numpy as jnp

from ._checks import check_scalar


class AbstractInvariantMonitor(eqx.Module):
    """An invariant of one state, checked at every save: the run of a body whose invariant
    `I` drifts to `max|I_k − I_0| > rtol·max|I_0| + atol` (∞-norms over the invariant's
    components) ends with `RESULTS.invariant_drift`."""

    rtol: float = 1e-3
    atol: float = 0.0

    def __check_init__(self):
        check_scalar("rtol", self.rtol, positive=True)
        check_scalar("atol", self.atol)
        if not self.atol >= 0:
            raise ValueError(f"`atol` must be ≥ 0, got {self.atol}.")

    @abc.abstractmethod
    def invariant(self, system, g, m):
        """The invariant of one state `(g, m)` of `system`, an array `(k,)`."""

    def drifted(self, reference, value):
        """Whether `value` is past the tolerance from `reference` (both `(k,)`)."""
        scale = jnp.max(jnp.abs(reference))
        return jnp.max(jnp.abs(value - reference)) > self.rtol * scale + self.atol


class EnergyMonitor(AbstractInvariantMonitor):
    """The total energy `H(m) + V(g)` (a system of several bodies: theirs summed, couplings
    included) kept within `rtol` of its initial value (relative) plus `atol`. Variational
    and splitting methods keep it bounded; a run past the tolerance has taken too large a
    step for what it met (e.g. a close encounter).

    **Arguments:** `rtol` (default `1e-3`), `atol` (default `0`)."""

    def invariant(self, system, g, m):
        energy = jnp.sum(system.energy(m))
        if system.potential is not None:
            energy = energy + system.potential_energy(g)
        return energy[None]


class MomentumMonitor(AbstractInvariantMonitor):
    """The momentum of the symmetry (`lievi.diagnostics.total_momentum`: the spatial
    momentum of one body, summed over the bodies of a system) kept within `rtol` of its
    initial size plus `atol` — conserved only where the potential keeps the symmetry (a
    free body, bodies coupled by their relative poses). Give `atol` for a state whose
    momentum is near zero.

    **Arguments:** `rtol` (default `1e-3`), `atol` (default `0`)."""

    def invariant(self, system, g, m):
        each = system.side.noether_momentum(system.group, g, m)
        return jnp.reshape(each, (-1, each.shape[-1])).sum(axis=0)


def as_monitor(monitor) -> AbstractInvariantMonitor | None:
    """`monitor` checked: `None` or an invariant monitor (`ValueError` otherwise)."""
    if monitor is not None and not isinstance(monitor, AbstractInvariantMonitor):
        raise ValueError(
            "`monitor` must be None or an invariant monitor, e.g. "
            f"lievi.EnergyMonitor(rtol=1e-3); got {type(monitor).__name__}."
        )
    return monitor
