"""Coupling potentials of N rigid bodies, functions of the poses `g` `(N, 4, 4)`.

Each body carries point sites at fixed body-frame positions `s_ia`; their world positions
are `x_ia = R_i s_ia + p_i`. The potentials below depend on the poses only through the
distances `|x_ia − x_jb|` between sites of different bodies, which a common rigid motion
of all bodies leaves unchanged: they are invariant under the diagonal action of SE(3),
so the total linear and angular momentum are conserved (`lievi.RigidBodies`). Pairs of
sites on one body are excluded (their distance is fixed: a constant energy).

- `SitePotential`: a pair energy (`lievi.LennardJones`, `lievi.Coulomb`, `lievi.Morse`,
  or several summed) over every pair of sites on different bodies — rigid molecules —
  optionally with a cut-off, in a periodic box, over a neighbour list (`_neighbors.py`;
  a box keeps the total linear momentum, not the angular);
- `SiteSprings`: springs between named sites — formations, tethers;
- `MutualGravity` (`_mutual_gravity.py`): Newtonian gravity between point-mass sets.

The torques and forces on each body are the derivatives of these energies along each
body's own motions, by autodiff (`AbstractLieSystem.force`). A pair of sites that
coincide gives an infinite energy (or a non-finite force), which `simulate` reports as
`RESULTS.nonfinite`.
"""

from __future__ import annotations

import copy

import equinox as eqx
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Bool, Float, Int

from .._checks import shown
from ._neighbors import is_pair, minimum_image, pair_list_conditions, shifted_force
from ._pair_energies import AbstractPairEnergy
from ._potential import AbstractPotential
from ._ragged import stack_bodies


def site_positions(g: Float[Array, "N 4 4"], sites: Float[Array, "N k 3"]):
    """The world positions `R_i s_ia + p_i` of the body-frame sites, shape `(N, k, 3)`."""
    return jnp.einsum("nij,nkj->nki", g[:, :3, :3], sites) + g[:, None, :3, 3]


def body_offset_pairs(n: int):
    """Every pair of sites on different bodies of `n` bodies, laid out by body offset:
    `(first, second, spread, weight)`. Pair `(δ, b, a, c)` is site `a` of body `b` and
    site `c` of body `(b + δ) mod n`, for `δ = 1, …, ⌊n/2⌋`: each pair of bodies once,
    except for even `n` those `n/2` apart, listed from both ends (`weight` ½ there, else
    1, `(D, 1, 1, 1)`). `first(v)`, `second(v)` of a per-site array `v` `(n, k, …)` are its
    values at the pairs' first and second sites, `(1, n, k, 1, …)` and `(D, n, 1, k, …)`;
    `spread(pull)` the site forces `(n, k, 3)` of forces `pull` `(D, n, k, k, 3)` on the
    first sites and their opposites on the second. Whole bodies are gathered (`n·D`
    rows of `k` sites), no site-by-site index pairs. The indices are computed in the
    program (not `n²/2`-sized constants in it)."""
    offsets = jnp.arange(1, n // 2 + 1)
    bodies = jnp.arange(n)
    partner = (bodies + offsets[:, None]) % n  # (D, n)
    source = (bodies - offsets[:, None]) % n  # the body whose partner at offset δ is b
    weight = jnp.where(2 * offsets == n, 0.5, 1.0)[:, None, None, None]

    def first(v):
        v = jnp.asarray(v)
        return v[None, :, :, None]

    def second(v):
        v = jnp.asarray(v)
        return v[partner][:, :, None, :]

    def spread(pull):
        # Body b's sites take Σ_c of their pulls; body b' takes minus the pulls on the
        # sites of the bodies δ places before it, gathered back by `source`.
        received = jnp.take_along_axis(jnp.sum(pull, axis=2), source[:, :, None, None], axis=1)
        return jnp.sum(pull, axis=(0, 3)) - jnp.sum(received, axis=0)

    return first, second, spread, weight


def listed_pairs(pairs, n: int, k: int):
    """The pairs of a neighbour list `(P, 2)` of flat site indices (padding rows with the
    index `n·k`), in the form of `body_offset_pairs`: `(first, second, spread, listed)`,
    `first(v)`, `second(v)` `(P, …)`, `listed` the rows that are pairs (padding rows read
    site 0 twice and count nothing)."""
    listed = is_pair(pairs, n * k)
    i = jnp.where(listed, pairs[:, 0], 0)
    j = jnp.where(listed, pairs[:, 1], 0)

    def first(v):
        v = jnp.asarray(v)
        return v.reshape(n * k, *v.shape[2:])[i]

    def second(v):
        v = jnp.asarray(v)
        return v.reshape(n * k, *v.shape[2:])[j]

    def spread(pull):
        forces = jnp.zeros((n * k, 3), pull.dtype).at[i].add(pull).at[j].add(-pull)
        return forces.reshape(n, k, 3)

    return first, second, spread, listed


def cross_body_pairs(n_bodies: int, n_sites: int):
    """Index arrays `(i, j)`, `i < j`, of the flattened sites (body-major) that lie on
    different bodies: every pair once, none within a body. NumPy, fixed by the shapes."""
    i, j = np.triu_indices(n_bodies * n_sites, k=1)
    keep = i // n_sites != j // n_sites
    return i[keep], j[keep]


def check_sites(sites, per_site: dict) -> None:
    shape = jnp.shape(sites)
    if len(shape) != 3 or shape[-1] != 3:
        raise ValueError(
            f"`sites` must have shape (N, k, 3) (k body-frame positions per body), got {shape}."
        )
    for name, value in per_site.items():
        if value is not None and jnp.shape(value) != shape[:2]:
            raise ValueError(
                f"`{name}` must have shape (N, k) = {shape[:2]}, one per site, got "
                f"{jnp.shape(value)}."
            )


class SitePotential(AbstractPotential):
    """`V(g) = Σ e(|x_ia − x_jb|)` over every pair of sites on different bodies.

    **Arguments:**

    - `sites`: body-frame positions `(N, k, 3)`, measured from each body's centre of mass;
      or, for bodies of different numbers of sites, a list of `N` arrays `(k_i, 3)`
      (with `types` and `charges` lists of `(k_i,)` alike), padded to `k = max k_i` with
      sites in no pair (`mask`).
    - `pair`: a pair energy (`lievi.LennardJones`, `lievi.Coulomb`, `lievi.Morse`) or a
      tuple of them (summed).
    - `types`: integer site types `(N, k)` (default all 0), in `[0, T)`, indexing the
      `(T, T)` parameter tables of the pair energies (symmetric tables).
    - `charges`: site charges `(N, k)`, for `lievi.Coulomb`.
    - `cutoff`: `r_c > 0`, or `None` (default: no cut-off). Pairs farther than `r_c`
      contribute nothing, and each pair energy is energy-and-force shifted,
      `e(r) − e(r_c) − (r − r_c) e'(r_c)`, so that energy and force vanish continuously at
      `r_c` and the integrator's energy error stays bounded (a plain truncation makes
      them jump whenever a pair crosses `r_c`).
    - `box`: the sides of an orthorhombic periodic box, a scalar or `(3,)`, `> 0`, or
      `None` (default: free space). Separations are taken to the nearest periodic image
      (`d − L·round(d/L)`), which needs `cutoff ≤ L/2` (then it is the only image within
      reach). Bodies' centres are not wrapped: poses move freely through the box walls,
      only the separations are imaged. The energy is invariant under translations (the
      total linear momentum is conserved) but not under rotations: the box has axes, and
      the total angular momentum is not conserved.
    - `neighbors`: a pair list `(P, 2)` of flat site indices (body-major, `body·k + site`),
      each pair of sites on different bodies once (in either order; twice is refused),
      rows with the index `N·k` in either column padding (contributing nothing), or `None`
      (default: every pair of sites on different bodies). Needs `cutoff`. Built by
      `lievi.BruteForceNeighbors` or `lievi.JaxMDNeighbors` with a skin, valid while no
      site has moved more than half the skin; `lievi.simulate_with_neighbor_list` rebuilds
      and checks it during a run.

    - `mask`: booleans `(N, k)`, `False` for a padding site, which takes part in no pair
      (default: every site real; from a list of `sites`, the sites given). A neighbour
      list may hold its pairs (they take capacity, not energy).

    Cost: one evaluation of `e` per pair, `N k (N − 1) k / 2` pairs without a neighbour
    list (twice that with a cut-off: `e(r_c)`, `e'(r_c)` per pair), `P` with one.
    """

    sites: Float[Array, "N k 3"]
    pair: tuple[AbstractPairEnergy, ...]
    types: Int[Array, "N k"]
    charges: Float[Array, "N k"] | None
    cutoff: Float[Array, ""] | None
    box: Float[Array, " 3"] | None
    neighbors: Int[Array, "P 2"] | None
    mask: Bool[Array, "N k"] | None
    # `neighbors` is a builder's list (`from_builder`), with no pair twice by
    # construction: its check for repeated pairs, a sort of the list, is left out.
    built: bool = eqx.field(static=True, default=False)

    def __init__(
        self,
        sites,
        pair,
        types=None,
        charges=None,
        *,
        cutoff=None,
        box=None,
        neighbors=None,
        mask=None,
    ):
        self.sites, given = stack_bodies("sites", sites, 0.0, (3,))
        if not given.all():  # bodies of different numbers of sites, padded
            mask = given if mask is None else np.asarray(mask) & given
        self.pair = tuple(pair) if isinstance(pair, (tuple, list)) else (pair,)
        shape = jnp.shape(self.sites)[:2]
        self.types = (
            jnp.zeros(shape, int)
            if types is None
            else stack_bodies("types", types, 0, dtype=None)[0]
        )
        self.charges = None if charges is None else stack_bodies("charges", charges, 0.0)[0]
        self.mask = None if mask is None else jnp.asarray(mask)
        self.cutoff = None if cutoff is None else jnp.asarray(cutoff, float)
        self.box = None if box is None else jnp.broadcast_to(jnp.asarray(box, float), (3,))
        self.neighbors = None if neighbors is None else jnp.asarray(neighbors)

    def __check_init__(self):
        check_sites(self.sites, {"types": self.types, "charges": self.charges, "mask": self.mask})
        if not jnp.issubdtype(self.types.dtype, jnp.integer):
            raise ValueError(f"`types` must be integers, got dtype {self.types.dtype}.")
        if self.mask is not None and self.mask.dtype != jnp.bool_:
            raise ValueError(f"`mask` must be booleans (N, k), got dtype {self.mask.dtype}.")
        for energy in self.pair:
            if not isinstance(energy, AbstractPairEnergy):
                raise ValueError(
                    "`pair` must be a pair energy (lievi.LennardJones, lievi.Coulomb, "
                    f"lievi.Morse) or a tuple of them, got {type(energy).__name__}."
                )
            if energy.needs_charges() and self.charges is None:
                raise ValueError(
                    f"{type(energy).__name__} reads the sites' charges: pass `charges` (N, k)."
                )
        self._check_box_and_neighbors()

    def _check_box_and_neighbors(self):
        if self.cutoff is not None and jnp.ndim(self.cutoff) != 0:
            raise ValueError(f"`cutoff` must be a scalar, got shape {jnp.shape(self.cutoff)}.")
        if self.box is not None and self.cutoff is None:
            raise ValueError(
                "A periodic `box` needs a `cutoff` ≤ half the box: the minimum-image energy "
                "without one jumps where a pair crosses half the box."
            )
        if self.neighbors is not None and self.cutoff is None:
            raise ValueError("`neighbors` needs a `cutoff` (the list holds the pairs within it).")
        if self.neighbors is not None:
            self._check_neighbors()

    def _check_neighbors(self):
        pairs = self.neighbors
        if pairs.ndim != 2 or pairs.shape[1] != 2 or not jnp.issubdtype(pairs.dtype, jnp.integer):
            raise ValueError(
                "`neighbors` must be integers of shape (P, 2), flat site indices, got shape "
                f"{pairs.shape} and dtype {pairs.dtype}."
            )

    def parameter_conditions(self):
        """Finite parameters, the pair energies' own conditions, site types within their
        tables, a positive cut-off at most half a positive box, and an admissible pair list
        (`pair_list_conditions`)."""
        conditions = super().parameter_conditions() + self._type_conditions()
        if self.cutoff is not None:
            conditions.append(
                (self.cutoff > 0, f"`cutoff` must be > 0{shown(self.cutoff, ', got {}')}.")
            )
        if self.box is not None:
            smallest = jnp.min(self.box)
            conditions += [
                (
                    jnp.all(self.box > 0),
                    f"`box` sides must all be > 0{shown(self.box, ', got {}')}.",
                ),
                (
                    self.cutoff <= smallest / 2,
                    f"`cutoff`{shown(self.cutoff, ' ({})')} must be at most half the smallest "
                    f"side of `box`{shown(smallest, ' ({})')}: beyond, a site would reach two "
                    "images of another. Use a larger box or a shorter cut-off.",
                ),
            ]
        if self.neighbors is not None:
            n, k = jnp.shape(self.sites)[:2]
            conditions += pair_list_conditions(self.neighbors, n * k, k, repeats=not self.built)
        return conditions

    def _type_conditions(self):
        """Each pair energy's conditions, and every site type an index into its tables."""
        types = self.types
        conditions = [(jnp.all(types >= 0), "`types` must be ≥ 0 (indices into the pair tables).")]
        largest = shown(jnp.max(types, initial=0), " {}")
        for energy in self.pair:
            conditions += energy.parameter_conditions()
            for name, table in energy.tables().items():
                size = jnp.shape(table)[0]
                conditions.append(
                    (
                        jnp.all(types < size),
                        f"{type(energy).__name__}.{name} is a table over {size} site types, "
                        f"but `types` uses type{largest} ≥ {size}: give a table over every "
                        "type in `types`, or fix `types`.",
                    )
                )
        return conditions

    def flat_positions(self, g):
        """The world positions of the sites, flattened body-major, `(N·k, 3)`."""
        n, k = jnp.shape(self.sites)[:2]
        return site_positions(g, jnp.asarray(self.sites, g.dtype)).reshape(n * k, 3)

    def with_neighbors(self, neighbors):
        """This potential summing over the pair list `neighbors` `(P, 2)` (from a
        builder, `lievi.BruteForceNeighbors` or `lievi.JaxMDNeighbors`)."""
        return SitePotential(
            self.sites,
            self.pair,
            self.types,
            self.charges,
            cutoff=self.cutoff,
            box=self.box,
            neighbors=neighbors,
            mask=self.mask,
        )

    def from_builder(self, neighbors):
        """This potential summing over `neighbors`, a list a builder made
        (`AbstractNeighborBuilder.build` or `rebuild`) inside a run's program: the
        pairs are swapped in without `__init__`'s eager checks, and the list's check for
        repeated pairs — a sort of the list, at every segment of a run — is left out (a
        builder lists each pair once); the other conditions of the list still hold
        traced (`pair_list_conditions`)."""
        listed = eqx.tree_at(lambda p: p.neighbors, self, neighbors, is_leaf=lambda x: x is None)
        # `built` is static (a different program, not a traced value): set on a copy, as
        # equinox's own unflattening sets fields (`eqx.tree_at` reaches leaves only).
        listed = copy.copy(listed)
        object.__setattr__(listed, "built", True)
        return listed

    def _pairs(self, g):
        """The pairs summed over: `(d, r2, counted, terms, spread)` — `d = x_i − x_j`
        `(..., 3)` (minimum image in a box), the squared distances `r2` (set to a safe
        value where a pair does not count), `counted` (booleans, or `None`: every pair
        counts), `terms(r2)` each pair's energy and the factor `e'(r)/r` of its pull
        (`AbstractPairEnergy.value_and_slope`; shifted at the cut-off, halved for a pair
        listed twice) before `counted`, and `spread(pull)` the site forces `(N, k, 3)` of
        forces `pull` `(..., 3)` on each pair's first site and their opposites on its
        second.

        Without a neighbour list the pairs are laid out by body offset
        (`body_offset_pairs`): each body's sites against those of the bodies 1, 2, …, N/2
        places on, whole bodies at a time, rather than one site at a time from a list of
        index pairs (whose gathers, and their scatters for the forces, were most of the
        cost of a small system's step)."""
        n, k = jnp.shape(self.sites)[:2]
        x = site_positions(g, jnp.asarray(self.sites, g.dtype))
        charges = jnp.zeros((n, k), g.dtype) if self.charges is None else self.charges
        if self.neighbors is None:
            first, second, spread, weight = body_offset_pairs(n)
            listed = True
        else:
            first, second, spread, listed = listed_pairs(self.neighbors, n, k)
            weight = None
        if self.mask is not None:  # a pair with a padding site is none
            listed = listed & first(self.mask) & second(self.mask)
        d = first(x) - second(x)
        if self.box is not None:
            d = minimum_image(d, self.box.astype(d.dtype))
        squared = jnp.sum(d * d, axis=-1)
        args = (first(self.types), second(self.types), first(charges), second(charges))
        if self.cutoff is None:
            cutoff, counted = None, None if self.mask is None else listed
            # A padding site may sit anywhere, on another body's site too: its pairs take
            # the distance 1 (both branches of `where` are differentiated), then count 0.
            if counted is not None:
                squared = jnp.where(counted, squared, 1.0)
        else:
            cutoff = self.cutoff.astype(squared.dtype)
            counted = listed & (squared < cutoff * cutoff)
            # Outside (and for padding rows, whose distance is 0) r² is set to r_c²: both
            # branches of `where` are differentiated.
            squared = jnp.where(counted, squared, cutoff * cutoff)

        def terms(r2):
            each = [
                e.value_and_slope(r2, *args)
                if cutoff is None
                else shifted_force(e, r2, cutoff, *args)
                for e in self.pair
            ]
            value, along = sum(v for v, _ in each), sum(a for _, a in each)
            if weight is None:
                return value, along
            return weight.astype(r2.dtype) * value, weight.astype(r2.dtype) * along

        return d, squared, counted, terms, spread

    def __call__(self, g):
        _, r2, counted, terms, _ = self._pairs(g)
        e = terms(r2)[0]  # the slopes are dropped by the compiler
        return jnp.sum(e if counted is None else jnp.where(counted, e, 0.0))

    def value_and_body_wrenches(self, g):
        """`V(g)` and each body's wrench `(N, 6)` from the site forces in closed form
        (`site_wrenches`): per pair, `e(r)` and `e'(r)/r` from `r²` in one pass
        (`AbstractPairEnergy.value_and_slope`), the force `−(e'(r)/r) d` on site `i` and
        its opposite on `j` — no square root where the energy needs none, no reverse pass
        through the pair table."""
        d, r2, counted, terms, spread = self._pairs(g)
        e, along = terms(r2)
        if counted is not None:
            e = jnp.where(counted, e, 0.0)
            along = jnp.where(counted, along, 0.0)
        forces = spread(-along[..., None] * d)  # the pull on each pair's first site
        return jnp.sum(e), site_wrenches(g, jnp.asarray(self.sites, g.dtype), forces)


def site_wrenches(g: Float[Array, "N 4 4"], sites: Float[Array, "N k 3"], forces):
    """Each body's body-frame wrench `(τ_i, F_i)` `(N, 6)` from world forces `f_ia`
    `(N, k, 3)` on its sites: with `φ_ia = R_iᵀ f_ia`, `F_i = Σ_a φ_ia` and
    `τ_i = Σ_a s_ia × φ_ia`, the generalised force `−dV` along `g_i exp(ε ξ)`, as
    `AbstractLieSystem.force` defines it (`dx_ia = R_i(ω × s_ia + v)`)."""
    body = jnp.einsum("nji,nkj->nki", g[:, :3, :3], forces)
    torque = jnp.sum(jnp.cross(sites, body), axis=1)
    return jnp.concatenate([torque, jnp.sum(body, axis=1)], axis=-1)


class SiteSprings(AbstractPotential):
    """Springs between named sites of different bodies: `V = Σ_s ½ k_s (|x_a − x_b| − L_s)²`.

    **Arguments:**

    - `sites`: body-frame positions `(N, k, 3)`.
    - `pairs`: integers `(S, 4)`, each row `(body_a, site_a, body_b, site_b)`, `body_a ≠
      body_b`.
    - `stiffness`: `k_s ≥ 0`, a scalar or `(S,)`.
    - `rest_length`: `L_s ≥ 0`, a scalar or `(S,)` (default 0).
    """

    sites: Float[Array, "N k 3"]
    pairs: Int[Array, "S 4"]
    stiffness: Float[Array, ...]
    rest_length: Float[Array, ...]

    def __init__(self, sites, pairs, stiffness, rest_length=0.0):
        self.sites = jnp.asarray(sites, float)
        self.pairs = jnp.asarray(pairs)
        self.stiffness = jnp.asarray(stiffness, float)
        self.rest_length = jnp.asarray(rest_length, float)

    def __check_init__(self):
        check_sites(self.sites, {})
        pairs = self.pairs
        if pairs.ndim != 2 or pairs.shape[1] != 4 or not jnp.issubdtype(pairs.dtype, jnp.integer):
            raise ValueError(
                "`pairs` must be integers of shape (S, 4), rows (body_a, site_a, body_b, "
                f"site_b), got shape {pairs.shape} and dtype {pairs.dtype}."
            )
        for name in ("stiffness", "rest_length"):
            value = getattr(self, name)
            if jnp.ndim(value) != 0 and jnp.shape(value) != (pairs.shape[0],):
                raise ValueError(
                    f"`{name}` must be a scalar or have shape ({pairs.shape[0]},), one per "
                    f"spring, got {jnp.shape(value)}."
                )

    def parameter_conditions(self):
        """Finite, `stiffness` and `rest_length` `≥ 0`, and each spring joining existing
        sites of two different bodies (an index out of range would be clamped by the
        gather: the spring would silently join other sites)."""
        n, k = jnp.shape(self.sites)[:2]
        pairs = self.pairs
        outside = jnp.any((pairs < 0) | (pairs >= jnp.array([n, k, n, k])), axis=1)
        within = pairs[:, 0] == pairs[:, 2]
        return super().parameter_conditions() + [
            (jnp.all(self.stiffness >= 0), "`stiffness` must be ≥ 0."),
            (jnp.all(self.rest_length >= 0), "`rest_length` must be ≥ 0."),
            (
                ~jnp.any(outside),
                f"`pairs`{shown(jnp.argmax(outside), ' row {}')} names a body or site outside "
                f"the {n} bodies of {k} sites (rows (body_a, site_a, body_b, site_b), each "
                "index from 0).",
            ),
            (
                ~jnp.any(within),
                f"`pairs`{shown(jnp.argmax(within), ' row {}')} joins two sites of one body "
                "(their distance is fixed): join sites of different bodies.",
            ),
        ]

    def __call__(self, g):
        x = site_positions(g, jnp.asarray(self.sites, g.dtype))
        d = x[self.pairs[:, 0], self.pairs[:, 1]] - x[self.pairs[:, 2], self.pairs[:, 3]]
        squared = jnp.sum(d * d, axis=-1)
        # A spring of rest length 0 may pass through zero length: its energy ½k|d|² is
        # smooth there, but √ is not (both branches of `where` are differentiated).
        positive = squared > 0
        length = jnp.where(positive, jnp.sqrt(jnp.where(positive, squared, 1.0)), 0.0)
        return jnp.sum(self.stiffness * (length - self.rest_length) ** 2) / 2
