"""Periodic boxes, cut-offs and neighbour lists of site potentials (`lievi.SitePotential`).

- **Minimum image.** In an orthorhombic periodic box of sides `L` a site interacts with
  the nearest periodic image of every other site: the separation `d` is replaced by
  `d − L·round(d/L)` (`minimum_image`; jax-md's `space.periodic` takes the same
  convention). With a cut-off `r_c ≤ L/2` that image is the only one within reach, so
  the energy is the sum over all images, truncated at `r_c`.
- **Cut-off** (`shifted_force`): the pair energy is replaced by the energy-and-force
  shifted one, `e(r) − e(r_c) − (r − r_c) e'(r_c)` for `r < r_c` and 0 beyond, whose
  value and derivative both vanish at `r_c`. A plain truncation makes the energy jump as a
  pair crosses `r_c`, a shift of the energy alone leaves the force jumping; either kicks
  the discrete energy by an amount of order the jump at every crossing, and the errors
  random-walk. The shifted-force energy is C¹, the force continuous, and a symplectic
  method's energy error stays bounded (measured in `tests/test_site_neighbors.py`).
- **Neighbour lists** (Verlet lists): the candidate pairs of sites on different bodies
  within `r_c + skin`, built at one configuration. The list holds every pair within
  `r_c` for as long as no site has moved more than `skin/2` since it was built (two
  sites then approach by less than `skin`). A builder (`BruteForceNeighbors`,
  `JaxMDNeighbors`) returns the pairs as an int array `(capacity, 2)` of flat site
  indices (body-major, `i < j`), padded with the fill index `N·k` (one past the last
  site), which the potential reads as "no pair": the array's shape stays fixed from one
  build to the next, so the compiled step is reused. `lievi.simulate_with_neighbor_list`
  rebuilds the list between segments of a run and checks both conditions.

Builders run outside the compiled step (between segments), on concrete positions.
"""

from __future__ import annotations

import abc
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np


def minimum_image(d, box):
    """The separation `d` (`(..., 3)`) to the nearest periodic image in an orthorhombic
    box of sides `box` (`(3,)`): `d − L·round(d/L)`, each component in `[−L/2, L/2]`."""
    return d - box * jnp.round(d / box)


def shifted_force(energy, r, cutoff, *args):
    """`e(r) − e(r_c) − (r − r_c) e'(r_c)`: the energy-and-force shifted pair energy, its
    value and slope zero at `r_c` (`e'` by forward-mode autodiff, per pair, so that
    parameter tables by site type are shifted pair by pair)."""
    at_cutoff = jnp.full_like(r, cutoff)
    e_c, slope_c = jax.jvp(lambda s: energy(s, *args), (at_cutoff,), (jnp.ones_like(r),))
    return energy(r, *args) - e_c - (r - at_cutoff) * slope_c


def fill_index(n_sites: int) -> int:
    """The padding index of a pair list: one past the last flat site."""
    return n_sites


class AbstractNeighborBuilder(eqx.Module):
    """Builds the neighbour list of a `lievi.SitePotential` with a cut-off at poses `g`.

    **Arguments:**

    - `skin`: the list holds the pairs within `cutoff + skin` (`> 0`). It stays valid while
      every site moves less than `skin/2`; a larger skin allows rarer rebuilds at the price
      of more candidate pairs (their number grows as `(cutoff + skin)³`).
    - `capacity`: the fixed number of rows of the list (`None`: on the first build,
      `capacity_factor` times the pairs found, rounded up). A build that finds more pairs
      raises a `ValueError` naming `capacity`.
    - `capacity_factor`: the headroom of an automatic capacity (default 1.2), for the
      pair count's growth between builds.

    Calling the builder, `builder(potential, g)`, returns the pairs `(capacity, 2)`;
    `potential.with_neighbors(pairs)` is the potential that sums over them.
    """

    skin: float = eqx.field(static=True)
    capacity: int | None = eqx.field(static=True, default=None)
    capacity_factor: float = eqx.field(static=True, default=1.2)

    def __check_init__(self):
        if not (isinstance(self.skin, (int, float)) and self.skin > 0):
            raise ValueError(f"`skin` must be a number > 0, got {self.skin!r}.")
        if self.capacity is not None and not (
            isinstance(self.capacity, int) and self.capacity >= 1
        ):
            raise ValueError(f"`capacity` must be an integer ≥ 1 or None, got {self.capacity!r}.")
        if not self.capacity_factor >= 1:
            raise ValueError(f"`capacity_factor` must be ≥ 1, got {self.capacity_factor!r}.")

    @abc.abstractmethod
    def candidates(self, x, body, radius: float, box):
        """`(i, j)`, NumPy integer arrays, `i < j`: every pair of the flat sites `x`
        `(n, 3)` on different bodies (`body` `(n,)`) closer than `radius` (the minimum
        image in `box` `(3,)`, or free space where `box` is `None`), each pair once."""

    def __call__(self, potential, g):
        if potential.cutoff is None:
            raise ValueError(
                "A neighbour list needs a cut-off: build the potential with "
                "`SitePotential(..., cutoff=r_c)`."
            )
        x = np.asarray(potential.flat_positions(jnp.asarray(g)))
        n_sites, k = x.shape[0], potential.sites.shape[1]
        box = None if potential.box is None else np.asarray(potential.box)
        i, j = self.candidates(x, np.arange(n_sites) // k, float(potential.cutoff) + self.skin, box)
        count = len(i)
        capacity = self.capacity
        if capacity is None:
            capacity = max(1, math.ceil(count * self.capacity_factor))
        if count > capacity:
            raise ValueError(
                f"The neighbour list needs {count} pairs, more than its `capacity` "
                f"({capacity}): pass a larger `capacity` to the builder (e.g. "
                f"{math.ceil(count * self.capacity_factor)}), or leave it None to size it "
                "on the first build."
            )
        order = np.lexsort((j, i))
        pairs = np.full((capacity, 2), fill_index(n_sites), dtype=np.int32)
        pairs[:count, 0], pairs[:count, 1] = i[order], j[order]
        return jnp.asarray(pairs)


class BruteForceNeighbors(AbstractNeighborBuilder):
    """The neighbour list by testing every pair of sites: `O((N k)²)` time per build, in
    blocks of rows (memory `O(N k)` per block); NumPy, no extra dependency. Fine up to a
    few thousand sites; beyond, `JaxMDNeighbors` (a cell list, `O(N k)`)."""

    def candidates(self, x, body, radius, box):
        n = x.shape[0]
        rows_per_block = max(1, 1_000_000 // max(n, 1))
        found_i, found_j = [], []
        columns = np.arange(n)
        for start in range(0, n, rows_per_block):
            rows = np.arange(start, min(n, start + rows_per_block))
            d = x[rows, None, :] - x[None, :, :]
            if box is not None:
                d = d - box * np.round(d / box)
            near = np.einsum("rcx,rcx->rc", d, d) < radius * radius
            near &= columns[None, :] > rows[:, None]
            near &= body[None, :] != body[rows][:, None]
            a, b = np.nonzero(near)
            found_i.append(rows[a])
            found_j.append(b)
        return np.concatenate(found_i), np.concatenate(found_j)


class JaxMDNeighbors(AbstractNeighborBuilder):
    """The neighbour list by jax-md's `partition.neighbor_list` (a cell list: `O(N k)`
    per build), in its ordered sparse format; pairs within one body are dropped after.

    Needs the optional dependency jax-md (`pip install "lievi[jaxmd]"`), imported when a
    list is built, never by `import lievi`. In a periodic box the sites are wrapped into
    the box for jax-md (the minimum-image separations, hence the pairs, are unchanged);
    in free space they are shifted into a bounding box with a margin of the list radius.
    """

    def candidates(self, x, body, radius, box):
        try:
            from jax_md import partition, space
        except ImportError as error:
            raise ImportError(
                'JaxMDNeighbors builds the list with jax-md: pip install "lievi[jaxmd]", '
                "or use lievi.BruteForceNeighbors (no extra dependency)."
            ) from error
        n = x.shape[0]
        if box is None:
            x = x - x.min(axis=0) + radius
            side = x.max(axis=0) + radius
            displacement, _ = space.free()
        else:
            side = np.broadcast_to(box, (3,))
            x = np.mod(x, side)
            displacement, _ = space.periodic(jnp.asarray(side))
        neighbor_fn = partition.neighbor_list(
            displacement,
            jnp.asarray(side),
            radius,
            dr_threshold=0.0,
            capacity_multiplier=1.0,
            format=partition.OrderedSparse,
        )
        i, j = np.asarray(neighbor_fn.allocate(jnp.asarray(x)).idx)
        present = (i < n) & (j < n)
        i, j = i[present], j[present]
        keep = body[i] != body[j]
        i, j = i[keep], j[keep]
        return np.minimum(i, j), np.maximum(i, j)
