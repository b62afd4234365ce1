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
  site), which the potential reads as "no pair" in either column (`is_pair`): the
  array's shape stays fixed from one build to the next, so the compiled step is reused.
  A list given by hand is checked as the potential's parameters are
  (`pair_list_conditions`): a pair within one body, or listed twice, is refused. `lievi.simulate_with_neighbor_list`
  rebuilds the list between segments of a run and checks both conditions.

A builder's first list is built on the host, on concrete positions (that sizes its
`capacity`, and jax-md allocates its buffers there); the later ones are built inside the
run's compiled program (`rebuild`; a builder with `candidates` only calls them back on the
host), so that a whole run of `lievi.simulate_with_neighbor_list` is one program.
"""

from __future__ import annotations

import abc
import functools
import math

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import Conditions, shown


def minimum_image(d, box):
    """The separation `d` (`(..., 3)`) to the nearest periodic image in an orthorhombic
    box of sides `box` (`(3,)`): `d − L·round(d/L)`, each component in `[−L/2, L/2]`."""
    return d - box * jnp.round(d / box)


def shifted_force(energy, r2, cutoff, *args):
    """`(e_s(r), e_s'(r)/r)` at the squared distances `r2` for the energy-and-force
    shifted pair energy `e_s(r) = e(r) − e(r_c) − (r − r_c) e'(r_c)`, whose value and slope
    are zero at `r_c` (`AbstractPairEnergy.value_and_slope`). The values at `r_c` are
    taken at the scalar `r_c²`: they are per pair only where the energy has parameter
    tables by site type or reads charges (broadcasting), one number for all pairs else."""
    cutoff = jnp.asarray(cutoff, r2.dtype)
    e, along = energy.value_and_slope(r2, *args)
    e_c, along_c = energy.value_and_slope(cutoff * cutoff, *args)
    slope_c = along_c * cutoff  # e'(r_c)
    inverse = jax.lax.rsqrt(r2)  # 1/r, and r = r² / r: one reciprocal square root
    return e - e_c - (r2 * inverse - cutoff) * slope_c, along - slope_c * inverse


def fill_index(n_sites: int) -> int:
    """The padding index of a pair list: one past the last flat site."""
    return n_sites


def is_pair(pairs, n_sites: int):
    """`(P,)` booleans: the rows of the pair list `pairs` `(P, 2)` that are pairs of sites.
    A row with the padding index in either column is padding, whichever column holds it."""
    return jnp.all(pairs < n_sites, axis=1)


def pair_list_conditions(pairs, n_sites: int, k: int, repeats: bool = True) -> Conditions:
    """The admissible pair lists `(P, 2)` of `n_sites` flat sites, `k` a body, as
    conditions (`lievi._checks.Conditions`): every index a site or the padding index, no
    pair within one body, and no pair listed twice — neither a repeated row nor the pair
    given both ways round, each of which would count its energy twice. A duplicate is
    refused rather than dropped: finding it costs a sort of the list, which the check
    does once a run and the energy would do at every force evaluation. A pair listed once
    in either order is the same pair (the energy is symmetric). `repeats=False` leaves
    the repeated pairs out: for a builder's list, which has none by construction."""
    fill = fill_index(n_sites)
    real = is_pair(pairs, n_sites)
    conditions = [
        (
            jnp.all((pairs >= 0) & (pairs <= fill)),
            f"`neighbors` holds indices outside [0, {n_sites}] (the {n_sites} flat sites "
            f"and the padding index {fill}).",
        ),
        (
            ~jnp.any(real & (pairs[:, 0] // k == pairs[:, 1] // k)),
            "`neighbors` pairs two sites of one body (their distance is fixed): list only "
            "sites of different bodies, as the builders do.",
        ),
    ]
    if pairs.shape[0] < 2 or not repeats:
        return conditions
    low, high = jnp.min(pairs, axis=1), jnp.max(pairs, axis=1)
    order = jnp.lexsort((high, low))  # equal pairs end up next to each other
    low, high, real = low[order], high[order], real[order]
    repeated = real[1:] & real[:-1] & (low[1:] == low[:-1]) & (high[1:] == high[:-1])
    row = shown(order[1:][jnp.argmax(repeated)], " (row {})")
    conditions.append(
        (
            ~jnp.any(repeated),
            f"`neighbors` lists a pair twice{row}, or both ways round: its energy would "
            "count twice. List each pair once, as the builders do.",
        )
    )
    return conditions


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

    def build(self, potential, g, state=None):
        """`(pairs, state)`: the list at poses `g` and what a later build may reuse
        (`state`, passed back in by `lievi.simulate_with_neighbor_list`; `None` the
        first time). The default builds from scratch by `candidates`."""
        x, body, radius, box = _inputs(potential, g, self.skin)
        i, j = self.candidates(x, body, radius, box)
        return jnp.asarray(_listed(i, j, len(x), self.sized(len(i)))), None

    def rebuild(self, potential, g, state):
        """`(pairs, state, overflow)`, traceable: the list at poses `g` from the `state` of
        an earlier `build` (whose `capacity` it keeps), and whether it overflowed — more
        pairs than `capacity`, or a buffer of the builder's own too small — in which case
        the pairs are incomplete and the list is built again on the host (`build`, which
        enlarges the buffers or raises naming `capacity`). The default calls `candidates`
        back on the host (`jax.pure_callback`)."""
        x = potential.flat_positions(g)
        n, k = x.shape[0], potential.sites.shape[1]
        radius = jnp.asarray(potential.cutoff, x.dtype) + self.skin
        box = None if potential.box is None else jnp.asarray(potential.box, x.dtype)

        def on_host(x, radius, box):
            box = None if box is None else np.asarray(box)
            i, j = self.candidates(np.asarray(x), np.arange(n) // k, float(radius), box)
            overflow = np.asarray(len(i) > self.capacity)  # the pairs then incomplete
            return _listed(i[: self.capacity], j[: self.capacity], n, self.capacity), overflow

        shapes = (
            jax.ShapeDtypeStruct((self.capacity, 2), jnp.int32),
            jax.ShapeDtypeStruct((), jnp.bool_),
        )
        pairs, overflow = jax.pure_callback(on_host, shapes, x, radius, box)
        return pairs, state, overflow

    def __call__(self, potential, g):
        return self.build(potential, g)[0]

    def sized(self, count: int) -> int:
        """The list's capacity for `count` pairs: `capacity`, or `capacity_factor ×
        count` where it is `None`; a `ValueError` naming `capacity` if it is too small."""
        capacity = self.capacity
        if capacity is None:
            capacity = max(1, math.ceil(count * self.capacity_factor))
        if count > capacity:
            raise ValueError(
                f"The neighbour list needs {count} pairs, more than its `capacity` "
                f"({capacity}): pass a larger `capacity` to the builder (e.g. "
                f"{math.ceil(count * self.capacity_factor)}), or a larger "
                "`capacity_factor` (an automatic capacity is that times the first build's "
                "pairs)."
            )
        return capacity


def _listed(i, j, n_sites: int, capacity: int):
    """The pairs `(i, j)` sorted by first site, then second, in a `(capacity, 2)` int32
    list padded with `fill_index(n_sites)`."""
    order = np.lexsort((j, i))
    pairs = np.full((capacity, 2), fill_index(n_sites), dtype=np.int32)
    pairs[: len(i), 0], pairs[: len(i), 1] = np.asarray(i)[order], np.asarray(j)[order]
    return pairs


def _inputs(potential, g, skin):
    """`(x, body, radius, box)`: the flat site positions (NumPy), each site's body, the
    list radius `cutoff + skin` and the box sides (or `None`)."""
    if potential.cutoff is None:
        raise ValueError(
            "A neighbour list needs a cut-off: build the potential with "
            "`SitePotential(..., cutoff=r_c)`."
        )
    x = np.asarray(_flat_positions(potential, jnp.asarray(g)))
    body = np.arange(x.shape[0]) // potential.sites.shape[1]
    box = None if potential.box is None else np.asarray(potential.box)
    return x, body, float(potential.cutoff) + skin, box


@eqx.filter_jit
def _flat_positions(potential, g):
    """`potential.flat_positions(g)` as one compiled program (eagerly, its einsum and
    reshapes are dispatched one by one at every build)."""
    return potential.flat_positions(g)


@jax.jit
def _kept_pairs(idx, body):
    """jax-md's ordered sparse pairs `(2, C)` as `(low, high, keep)`: real pairs of sites
    on different bodies (jax-md pads with the index `n`)."""
    n = body.shape[0]
    i, j = idx[0], idx[1]
    keep = (i < n) & (j < n)
    keep &= body[jnp.where(keep, i, 0)] != body[jnp.where(keep, j, 0)]
    return jnp.minimum(i, j), jnp.maximum(i, j), keep


@functools.partial(jax.jit, static_argnums=2)
def _compacted(low_high_keep, n, capacity):
    """The kept pairs, in jax-md's order (by first site), in the first rows of a
    `(capacity, 2)` list padded with `fill_index(n)`."""
    low, high, keep = low_high_keep
    fill = fill_index(n)
    (rows,) = jnp.nonzero(keep, size=capacity, fill_value=low.shape[0])
    low = jnp.append(low, fill)[rows]
    high = jnp.append(high, fill)[rows]
    return jnp.stack([low, high], axis=1).astype(jnp.int32)


class BruteForceNeighbors(AbstractNeighborBuilder):
    """The neighbour list by testing every pair of sites, in JAX on the default device
    (`_near_pairs`): `O((N k)²)` time and `(N k)²` bytes per build, no extra dependency.
    On a GPU a build of 10⁴ sites takes milliseconds; on a CPU it suits a few thousand
    sites. Beyond, `JaxMDNeighbors` (a cell list, `O(N k)`)."""

    def candidates(self, x, body, radius, box):
        near = np.asarray(_near_pairs(*_device_inputs(x, body, radius, box)))
        return np.nonzero(near)

    def build(self, potential, g, state=None):
        return _all_pairs_list(self, *_inputs(potential, g, self.skin)), None

    def rebuild(self, potential, g, state):
        pairs, overflow = _traced_all_pairs(self, potential, potential.flat_positions(g))
        return pairs, state, overflow


def _traced_all_pairs(builder, potential, x):
    """`(pairs, overflow)`: the `(capacity, 2)` list of the flat sites `x` by testing
    every pair, traceable (`builder.capacity` fixed by a first build)."""
    body = jnp.arange(x.shape[0]) // potential.sites.shape[1]
    radius = jnp.asarray(potential.cutoff, x.dtype) + builder.skin
    box = None if potential.box is None else jnp.asarray(potential.box, x.dtype)
    near = _near_pairs(x, body, radius, box)
    count = jnp.sum(near, dtype=jnp.int32)
    return _mask_to_pairs(near, builder.capacity), count > builder.capacity


def _all_pairs_list(builder, x, body, radius, box):
    """The `(capacity, 2)` list by testing every pair (`_near_pairs`). The mask, its count
    and the compacted list stay on the device: only the pair count (for `builder`'s
    capacity) comes back to the host."""
    near = _near_pairs(*_device_inputs(x, body, radius, box))
    return _mask_to_pairs(near, builder.sized(int(jnp.sum(near, dtype=jnp.int32))))


def _device_inputs(x, body, radius, box):
    box = None if box is None else jnp.asarray(box, dtype=x.dtype)
    return jnp.asarray(x), jnp.asarray(body), jnp.asarray(radius, dtype=x.dtype), box


# Pair distances computed at a time by `_near_pairs` (a block of rows against all
# columns): 4·10⁶ separations, 96 MB in float64.
_BLOCK_PAIRS = 4_000_000


@jax.jit
def _near_pairs(x, body, radius, box):
    """`(n, n)` booleans: `[i, j]` for `i < j` on different bodies within `radius` (the
    minimum image where `box` is given), computed in blocks of rows (`lax.map`) so that
    only the booleans are of size `n²`."""
    n = x.shape[0]
    rows = max(1, min(n, _BLOCK_PAIRS // max(n, 1)))
    blocks = -(-n // rows)
    # Padding rows have an index ≥ n: `j > i` keeps none of their pairs.
    x_rows = jnp.pad(x, ((0, blocks * rows - n), (0, 0)))
    body_rows = jnp.pad(body, (0, blocks * rows - n))
    columns = jnp.arange(n)

    def block(k):
        start = k * rows
        xi = jax.lax.dynamic_slice_in_dim(x_rows, start, rows)
        bi = jax.lax.dynamic_slice_in_dim(body_rows, start, rows)
        d = xi[:, None, :] - x[None, :, :]
        if box is not None:
            d = minimum_image(d, box)
        i = start + jnp.arange(rows)
        near = jnp.sum(d * d, axis=-1) < radius * radius
        return near & (columns[None, :] > i[:, None]) & (body[None, :] != bi[:, None])

    return jax.lax.map(block, jnp.arange(blocks)).reshape(blocks * rows, n)[:n]


@functools.partial(jax.jit, static_argnums=1)
def _mask_to_pairs(near, capacity):
    """The pairs of `near` in row-major order (by first site, then second; jax-md's and
    `AbstractNeighborBuilder.build`'s order) in a `(capacity, 2)` list padded with
    `fill_index(n)`."""
    fill = fill_index(near.shape[0])
    i, j = jnp.nonzero(near, size=capacity, fill_value=fill)
    return jnp.stack([i, j], axis=1).astype(jnp.int32)


class JaxMDNeighbors(AbstractNeighborBuilder):
    """The neighbour list by jax-md's `partition.neighbor_list` (a cell list: `O(N k)`
    per build), in its ordered sparse format; pairs within one body are dropped after.

    Needs the optional dependency jax-md (`pip install "lievi[jaxmd]"`), imported when a
    list is built, never by `import lievi`. In a periodic box the sites are wrapped into
    the box for jax-md (the minimum-image separations, hence the pairs, are unchanged);
    in free space they are shifted into a bounding box with a margin of the list radius.
    A periodic box shorter than three list radii (`cutoff + skin`) along a side holds no
    cell list: there every pair is tested, as by `BruteForceNeighbors`.
    """

    def candidates(self, x, body, radius, box):
        pairs, _ = self._from_jax_md(x, body, radius, box, None)
        real = np.asarray(pairs)
        real = real[real[:, 1] < len(x)]
        return real[:, 0], real[:, 1]

    def rebuild(self, potential, g, state):
        """jax-md's compiled `update` from the last list, in the program. Where the first
        build tested every pair (a small box: `state` is `None`), or in free space where a
        site has left the bounding box of the last allocation (which only the host can
        redo), every pair is tested instead, on the device: the same pairs. jax-md's own
        buffers overflowing is reported as an overflow (the host reallocates them)."""
        x = potential.flat_positions(g)
        if state is None:
            pairs, overflow = _traced_all_pairs(self, potential, x)
            return pairs, state, overflow
        update, neighbors, origin, side = state
        body = jnp.arange(x.shape[0]) // potential.sites.shape[1]

        def cells(neighbors):
            neighbors = update(shifted, neighbors)
            kept = _kept_pairs(neighbors.idx, body)
            overflow = (jnp.sum(kept[2]) > self.capacity) | (neighbors.did_buffer_overflow != 0)
            return _compacted(kept, x.shape[0], self.capacity), neighbors, overflow

        if potential.box is not None:
            shifted = jnp.mod(x, jnp.asarray(side, x.dtype))
            pairs, neighbors, overflow = cells(neighbors)
        else:
            shifted = x - jnp.asarray(origin, x.dtype)
            inside = jnp.all((shifted >= 0) & (shifted < jnp.asarray(side, x.dtype)))

            def every_pair(neighbors):
                pairs, overflow = _traced_all_pairs(self, potential, x)
                return pairs, neighbors, overflow

            pairs, neighbors, overflow = jax.lax.cond(inside, cells, every_pair, neighbors)
        return pairs, (update, neighbors, origin, side), overflow

    def build(self, potential, g, state=None):
        """Allocates jax-md's list on the first build (or after jax-md reports an
        overflow of its own buffers, or in free space a site left the bounding box);
        later builds are jax-md's compiled `update` from the previous list."""
        x, body, radius, box = _inputs(potential, g, self.skin)
        return self._from_jax_md(x, body, radius, box, state)

    def _from_jax_md(self, x, body, radius, box, state):
        try:
            from jax_md import partition, space
        except ImportError as error:
            raise ImportError(
                'JaxMDNeighbors builds the list with jax-md: pip install "lievi[jaxmd]", '
                "or use lievi.BruteForceNeighbors (no extra dependency)."
            ) from error
        if box is not None and not np.all(radius < np.broadcast_to(box, (3,)) / 3):
            # jax-md's cell list needs three cells of side `radius` along each side of
            # the box; in a smaller box it tests every pair instead, and there scatters
            # int64 indices into its int32 list in float64 mode (a JAX FutureWarning,
            # an error in later JAX releases). The same all-pairs test, done here.
            return _all_pairs_list(self, x, body, radius, box), None
        if state is not None:
            update, neighbors, origin, side = state
            shifted = _into_box(x, origin, side, box)
            if shifted is not None:
                neighbors = update(jnp.asarray(shifted), neighbors)
                if bool(neighbors.did_buffer_overflow):
                    state = None
            else:
                state = None
        if state is None:
            if box is None:  # a bounding box with a margin, the sites shifted into it
                origin = x.min(axis=0) - 2 * radius
                side = x.max(axis=0) - origin + 2 * radius
            else:
                origin, side = np.zeros(3), np.broadcast_to(box, (3,))
            allocate, update, allocated = _jax_md_list(
                partition, space, tuple(map(float, side)), radius, box is not None
            )
            inside = _into_box(x, origin, side, box)
            shifted = jnp.asarray(inside)
            # jax-md's `allocate` sizes its buffers on the host (seconds for 10⁴ sites on
            # a CPU, at every run's first build); a list allocated for as many sites in
            # the same box is updated instead (`update` recomputes every pair from the
            # positions: the same list), allocated anew only where it overflows. A list
            # built at the very same positions is the list: kept, not recomputed (a run
            # from the state of the last one's start, as a sweep over `h` or repeated
            # timings make it; an update is about a second for 10⁴ sites on a CPU).
            neighbors, at = allocated.get(len(x), (None, None))
            if neighbors is not None and not np.array_equal(at, inside):
                neighbors = update(shifted, neighbors)
            if neighbors is None or bool(neighbors.did_buffer_overflow):
                neighbors = allocate(shifted)
            allocated[len(x)] = (neighbors, inside)
        kept = _kept_pairs(neighbors.idx, jnp.asarray(body))
        capacity = self.sized(int(jnp.sum(kept[2])))
        pairs = _compacted(kept, len(x), capacity)
        return pairs, (update, neighbors, origin, side)


@functools.lru_cache(maxsize=8)
def _jax_md_list(partition, space, side: tuple, radius: float, periodic: bool):
    """jax-md's `(allocate, jitted update, allocated)` for a box and radius, kept across
    builds and runs so that `update` compiles once; `allocated` holds the last list by
    number of sites and the positions it was built at, for a later run's first build to
    update (or, at the same positions, keep) rather than allocate."""
    box = jnp.asarray(side)
    displacement, _ = space.periodic(box) if periodic else space.free()
    neighbor_fn = partition.neighbor_list(
        displacement,
        box,
        radius,
        dr_threshold=0.0,
        capacity_multiplier=1.25,
        format=partition.OrderedSparse,
    )
    return neighbor_fn.allocate, jax.jit(neighbor_fn.update), {}


def _into_box(x, origin, side, box):
    """The sites in jax-md's box: wrapped into a periodic box; in free space shifted by
    `origin`, or `None` where one left the bounding box `[0, side)`."""
    if box is not None:
        return np.mod(x, side)
    shifted = x - origin
    return shifted if bool(np.all((shifted >= 0) & (shifted < side))) else None
