"""Articulated bodies: rigid bodies joined by ball and hinge joints in a tree, on SE(3)ᴺ.

Maximal coordinates (docs/articulated.md): each body `i` is a free rigid body with a pose
`g_i = [[R_i, x_i], [0, 1]]` (origin at its centre of mass) and a body-frame momentum
`m_i = (Π_i, P_i)`, exactly as in `lievi.RigidBodies`; the joints are holonomic
constraints `Φ(g) = 0` on the poses (`lievi.BallJoint`, `lievi.HingeJoint`), enforced by
Lagrange multipliers. The constrained Euler–Poincaré equations are

    ṁ_i = ad_{ξ_i}ᵀ m_i + M_i(g) + (C(g)ᵀ λ)_i,   ġ_i = g_i ξ̂_i,   Φ(g) = 0,

with `C(g)` the constraint Jacobian along the left-trivialised directions,
`C η = d/dε Φ(g_1 exp(ε η̂_1), …)|₀`, and `λ` the joint reactions. `lievi.RATTLE` steps
them. The tree is static: `parents[i]` is the parent body of body `i`, or `-1` for the
world (a fixed base: a joint to the world; a floating base: no joint, `None`).
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np
from jaxtyping import Array, Float, Scalar

from .._checks import is_concrete
from .._groups._base import MatrixLieGroup
from .._groups._se3 import SE3
from ._base import AbstractLieSystem
from ._joint_dynamics import constrained_rate, project, project_state
from ._joint_rows import JointRows
from ._joints import AbstractJoint
from ._potential import AbstractPotential, as_potential
from ._rigid_bodies import RigidBodies, bodies_force
from ._side import Side
from ._tree_solve import tree_structure


class BodiesGravity(AbstractPotential):
    """Uniform gravity on bodies whose origins are their centres of mass, plus an optional
    potential: `V(g) = γ Σ_i m_i e₃·x_i + V₀(g)` (gravity along `−e₃`)."""

    mass: Float[Array, " N"]
    gravity: Float[Array, ""]
    extra: AbstractPotential | None

    def _gravity(self, g):
        """`γ Σ_i m_i e₃·x_i`, gravity's part of `V(g)`."""
        return jnp.asarray(self.gravity) * jnp.sum(jnp.asarray(self.mass) * g[..., :, 2, 3])

    def __call__(self, g):
        value = self._gravity(g)
        return value if self.extra is None else value + self.extra(g)

    def value_and_body_wrenches(self, g):
        """`(V(g), M(g))` in closed form: body `i`'s weight `γ m_i` acts at its centre of
        mass, its origin, so its wrench is no torque and the force `−γ m_i R_iᵀe₃` (`R_iᵀe₃`
        the third row of `R_i`); plus the further potential's, where it has a closed form
        (else `None`: the whole force by autodiff, which each RATTLE step traced twice)."""
        extra = None if self.extra is None else self.extra.value_and_body_wrenches(g)
        if self.extra is not None and extra is None:
            return None
        weight = jnp.asarray(self.gravity) * jnp.asarray(self.mass)
        value = self._gravity(g)
        up = g[..., :, 2, :3]
        wrench = jnp.concatenate([jnp.zeros_like(up), -weight[..., None] * up], axis=-1)
        return (value, wrench) if extra is None else (value + extra[0], wrench + extra[1])

    def parameter_conditions(self):
        extra = [] if self.extra is None else self.extra.parameter_conditions()
        return super().parameter_conditions() + extra


def _check_tree(parents, n: int) -> tuple[int, ...]:
    """`parents` as a tuple of ints, each `-1` (the world) or another body, without cycles;
    else a `ValueError` naming `parents`."""
    try:
        parents = tuple(int(p) for p in parents)
    except TypeError as error:
        raise ValueError(
            f"`parents` must be a sequence of {n} integers, got {parents!r}."
        ) from error
    if len(parents) != n:
        raise ValueError(f"`parents` must have one entry per body ({n}), got {len(parents)}.")
    for i, p in enumerate(parents):
        if not -1 <= p < n or p == i:
            raise ValueError(
                f"`parents[{i}]` = {p}: each parent must be another body (0 … {n - 1}) or -1 "
                "(the world)."
            )
    for i in range(n):
        path, j = [i], parents[i]
        while j != -1:
            if j in path:
                loop = " → ".join(map(str, path[path.index(j) :] + [j]))
                raise ValueError(
                    f"`parents` has a cycle ({loop}): a tree's bodies reach the world (-1) by "
                    "following their parents. Closed loops are not supported."
                )
            path.append(j)
            j = parents[j]
    return parents


def _depth_order(parents) -> tuple[int, ...]:
    """The bodies ordered so that each comes after its parent."""

    def depth(i):
        return 0 if parents[i] == -1 else 1 + depth(parents[i])

    return tuple(sorted(range(len(parents)), key=depth))


class ArticulatedBodies(AbstractLieSystem):
    """Rigid bodies joined by ball and hinge joints in a tree (chains, branching trees), with
    a fixed or floating base: a constrained left-invariant system on SE(3)ᴺ.

    **Arguments:**

    - `inertia`: principal moments `(N, 3)` or tensors `(N, 3, 3)` about each body's
      centre of mass, body frame.
    - `mass`: the masses `(N,)`, each `> 0`.
    - `parents`: `N` integers, `parents[i]` the parent body of body `i` or `-1` (the
      world). Static; it must be a tree (no cycles).
    - `joints`: `N` entries, `joints[i]` the joint between body `i` and its parent, a
      `lievi.BallJoint` or `lievi.HingeJoint` (for a joint to the world its parent point
      and axis are in the world frame), or `None` for a floating base (`parents[i] = -1`).
    - `gravity`: uniform gravity `γ` along `−e₃` of the world (default `None`: none).
    - `potential`: any further potential `V(g)` of the poses `(N, 4, 4)` (springs, …).

    The state is `g` `(N, 4, 4)` and `m` `(N, 6)` as for `lievi.RigidBodies`; it must
    satisfy the joints (`place` and `momentum` build one). Run it with `lievi.RATTLE`
    (or a `lievi.Composition` of it: variational, the momenta of the symmetries kept to
    round-off), or with an explicit `lievi.RKMK4`, `RKMK5` or `RKMK8` (the joints'
    reaction in the rate, the state projected back onto the joints after each step:
    high order, cheaper at tight accuracy, its momenta and energy drifting at the
    method's accuracy). The other methods do not know the joints.
    """

    bodies: RigidBodies
    joints: tuple[AbstractJoint | None, ...]
    gravity: Float[Array, ""] | None
    applied: AbstractPotential | None
    parents: tuple[int, ...] = eqx.field(static=True)
    group: MatrixLieGroup = eqx.field(static=True)
    side: Side = eqx.field(static=True)

    def __init__(self, inertia, mass, parents, joints, *, gravity=None, potential=None):
        self.bodies = RigidBodies(inertia, mass)
        n = self.bodies.n_bodies
        self.parents = _check_tree(parents, n)
        joints = tuple(joints)
        if len(joints) != n:
            raise ValueError(f"`joints` must have one entry per body ({n}), got {len(joints)}.")
        for i, (p, joint) in enumerate(zip(self.parents, joints)):
            if joint is None and p != -1:
                raise ValueError(
                    f"`joints[{i}]` is None but body {i} has parent {p}: only a root "
                    "(parent -1) may float free; give a BallJoint or HingeJoint."
                )
            if joint is not None and not isinstance(joint, AbstractJoint):
                raise ValueError(
                    f"`joints[{i}]` must be a lievi.BallJoint, a lievi.HingeJoint or None, "
                    f"got {type(joint).__name__}."
                )
        self.joints = joints
        self.gravity = None if gravity is None else jnp.asarray(gravity, float)
        self.applied = as_potential(potential)
        self.group = SE3
        self.side = Side.LEFT

    @property
    def potential(self) -> AbstractPotential | None:
        """Gravity on the bodies' masses plus the given potential, built from the one
        `mass` leaf (`bodies.mass`): a fit or a gradient with respect to the masses moves
        their weights with them."""
        if self.gravity is None:
            return self.applied
        return BodiesGravity(self.bodies.mass, self.gravity, self.applied)

    # ---- the free bodies -----------------------------------------------------------------

    @property
    def n_bodies(self) -> int:
        return self.bodies.n_bodies

    @property
    def mass(self):
        return self.bodies.mass

    @property
    def inertia(self):
        return self.bodies.inertia

    @property
    def tensor(self):
        return self.bodies.tensor

    def element_shape(self):
        return self.bodies.element_shape()

    def momentum_shape(self):
        return self.bodies.momentum_shape()

    def parameter_conditions(self):
        """The bodies' (finite, inertia SPD, mass `> 0`), the joints' (finite) and the
        potential's."""
        return super().parameter_conditions() + self.bodies.parameter_conditions()

    def lagrangian(self, xi):
        return self.bodies.lagrangian(xi)

    def legendre(self, xi):
        return self.bodies.legendre(xi)

    def velocity(self, m):
        return self.bodies.velocity(m)

    def energy(self, m) -> Scalar:
        """The kinetic energy (`lievi.diagnostics.energy` adds the potential)."""
        return self.bodies.energy(m)

    def force(self, g):
        """Each body's wrench from the potential, as `lievi.RigidBodies.force`: gravity's
        in closed form."""
        return bodies_force(self, g)

    def check_unconstrained(self, method: str) -> None:
        """A `ValueError`: the joints are constraints that `method` (a kick method's free
        step, `lievi.RK4` in the matrix embedding or the reference solution of the free
        Euler–Poincaré equations) would ignore, letting them drift apart."""
        raise ValueError(
            "ArticulatedBodies: the joints are constraints that only lievi.RATTLE and the "
            f"RKMK methods enforce; {method} would step the bodies as if they were free. Run "
            "it with `lievi.RATTLE()` (or `lievi.Composition(lievi.RATTLE(), 4)`), or with "
            "`lievi.RKMK4()`/`lievi.RKMK8()` (explicit, projected onto the joints)."
        )

    def free_flow(self, integrator, g, m, h: Scalar):
        self.check_unconstrained(type(integrator).__name__)

    def constrained_rate(self, g, m, m_dot):
        """`m_dot` with the joints' reaction `C(g)ᵀλ` that keeps the accelerations on the
        joints (index reduction; `lievi/_systems/_joint_dynamics.py`)."""
        return m_dot if self.n_constraints == 0 else constrained_rate(self, g, m, m_dot)

    def project_state(self, g, m):
        """`(g, m, held)`: the poses moved back onto the joints along the kinetic metric,
        the momenta onto their velocity constraints, `held` whether the joints then hold
        to round-off."""
        if self.n_constraints == 0:
            return g, m, jnp.asarray(True)
        return project_state(self, g, m)

    # ---- the joints ------------------------------------------------------------------------

    @property
    def n_constraints(self) -> int:
        return sum(0 if j is None else j.size for j in self.joints)

    def length_scale(self) -> Scalar:
        """`ℓ`: the largest distance from a centre of mass to one of its joint points (the
        link length the constraint tolerances are relative to; 1 if there is none)."""
        points = [jnp.zeros(3)]
        for p, joint in zip(self.parents, self.joints):
            if joint is None:
                continue
            points.append(joint.child_point)
            if p != -1:
                points.append(joint.parent_point)
        # One stacked norm, not one per point: this runs inside every iteration.
        largest = jnp.max(jnp.linalg.norm(jnp.stack(points), axis=-1))
        return jnp.where(largest > 0, largest, 1.0)

    def constraints(self, g: Float[Array, "N 4 4"]) -> Float[Array, " c"]:
        """`Φ(g)`, the joints' equations stacked in body order (length units).

        The joints of one kind are evaluated together: their parameters stacked and the
        one joint's `residual` mapped over them (`jax.vmap`), so the cost in operations
        does not grow with the number of joints (the iteration of `lievi.RATTLE`
        evaluates this several times per step)."""
        if self.n_constraints == 0:
            return jnp.zeros((0,), g.dtype)
        length = self.length_scale()
        # The world is the pose after the last body: a joint to it indexes `N`.
        poses = jnp.concatenate([g, jnp.eye(4, dtype=g.dtype)[None]])
        parts = []
        for bodies, parent_index in self._joint_groups():
            stacked = jax.tree.map(lambda *x: jnp.stack(x), *[self.joints[i] for i in bodies])
            values = jax.vmap(lambda joint, a, b: joint.residual(a, b, length))(
                stacked, poses[np.array(parent_index)], g[np.array(bodies)]
            )
            parts.append(values.reshape(-1))
        return jnp.concatenate(parts)[self._body_order()]

    def _joint_groups(self) -> list[tuple[tuple[int, ...], tuple[int, ...]]]:
        """For each kind of joint, `(bodies, parents)`: the bodies it joins to their
        parents, and those parents' indices into the poses with the world at `N`."""
        groups: dict[type, list[int]] = {}
        for i, joint in enumerate(self.joints):
            if joint is not None:
                groups.setdefault(type(joint), []).append(i)
        n = self.n_bodies
        return [
            (tuple(bodies), tuple(n if self.parents[i] == -1 else self.parents[i] for i in bodies))
            for bodies in groups.values()
        ]

    def _body_order(self) -> np.ndarray:
        """The permutation from the joints' equations grouped by kind to body order."""
        offsets, start = {}, 0
        for bodies, _ in self._joint_groups():
            for i in bodies:
                offsets[i] = start
                start += self.joints[i].size
        return np.concatenate(
            [offsets[i] + np.arange(j.size) for i, j in enumerate(self.joints) if j is not None]
        )

    def constraint_jacobian(self, g: Float[Array, "N 4 4"]) -> Float[Array, "c N 6"]:
        """`C(g)`: `C η = d/dε Φ(…, g_i exp(ε η̂_i), …)|₀`, each joint's rows in closed form
        (`AbstractJoint.jacobian`), the joints of one kind together as in `constraints`,
        set into the columns of their two bodies (a joint to the world has one).

        Closed form rather than `jax.jacfwd` of `constraints`: the forward-mode Jacobian
        of the `6N` directions, batched, was the largest part of a `lievi.RATTLE` step
        that builds it twice (at the start of the step and for its projection)."""
        n, c = self.n_bodies, self.n_constraints
        if c == 0:
            return jnp.zeros((0, n, 6), g.dtype)
        return self.constraint_rows(g).dense()

    def constraint_rows(self, g: Float[Array, "N 4 4"]) -> JointRows:
        """`C(g)` by joint (`JointRows`): each joint's closed-form rows on its two bodies,
        the joints of one kind evaluated together as in `constraints`. `lievi.RATTLE`
        multiplies with these, never with the dense `(c, N, 6)` array."""
        length = self.length_scale().astype(g.dtype)
        poses = jnp.concatenate([g, jnp.eye(4, dtype=g.dtype)[None]])
        blocks = {}
        for bodies, parent_index in self._joint_groups():
            stacked = jax.tree.map(lambda *x: jnp.stack(x), *[self.joints[i] for i in bodies])
            of_parent, of_child = jax.vmap(lambda joint, a, b: joint.jacobian(a, b, length))(
                stacked, poses[np.array(parent_index)], g[np.array(bodies)]
            )
            for k, i in enumerate(bodies):
                blocks[i] = (of_parent[k], of_child[k])
        joined = [i for i, joint in enumerate(self.joints) if joint is not None]
        return JointRows(
            self.n_bodies,
            joined,
            [self.parents[i] for i in joined],
            [blocks[i][0] for i in joined],
            [blocks[i][1] for i in joined],
        )

    def joint_structure(self):
        """The joints' tree as `tree_solver` reads it (`tree_structure`): each joint's rows
        of `constraints`, the order to eliminate them and the joints sharing a body."""
        return tree_structure(self.parents, [0 if j is None else j.size for j in self.joints])

    def velocity_constraints(self, g, m) -> Float[Array, " c"]:
        """`Φ̇ = C(g) ξ` with `ξ` the velocity of `m` (length per time)."""
        xi = self.velocity(m)
        return jnp.einsum("cnk,nk->c", self.constraint_jacobian(g), xi)

    @eqx.filter_jit
    def project_momentum(self, g, m) -> Float[Array, "N 6"]:
        """`m + C(g)ᵀμ` with `μ` such that `C(g) ξ = 0`: the momentum with the joints'
        velocity constraints satisfied, nearest to `m` in the kinetic metric."""
        return self.project_with_impulse(g, m)[0]

    def project_with_impulse(self, g, m, rows: JointRows | None = None):
        """`(m + C(g)ᵀμ, μ)`: `project_momentum` and the impulse `μ` `(c,)` it applied
        (`lievi.RATTLE` starts its next step's reaction from it). `rows`: `C(g)`
        (`constraint_rows`) where the caller has it already."""
        if self.n_constraints == 0:
            return m, jnp.zeros((0,), m.dtype)
        return project(self, self.constraint_rows(g) if rows is None else rows, m)

    # ---- building states ---------------------------------------------------------------------
    # `place` and `momentum` (and `project_momentum` above) are compiled as one program each
    # (`eqx.filter_jit`): called eagerly, as a user builds a run's start, their operations
    # one by one were 12 and 98 small programs.

    @eqx.filter_jit
    def place(self, rotations, base=None) -> Float[Array, "N 4 4"]:
        """The poses `g` `(N, 4, 4)` with the given rotations `(N, 3, 3)` whose joint points
        coincide: each body placed from its parent along the tree, a floating root at
        `base` (its centre of mass, default the origin; `(n_roots, 3)` for several)."""
        R = jnp.asarray(rotations)
        x = [None] * self.n_bodies
        free = iter(jnp.zeros((self.n_bodies, 3)) if base is None else jnp.atleast_2d(base))
        for i in _depth_order(self.parents):
            p, joint = self.parents[i], self.joints[i]
            if joint is None:
                x[i] = next(free)
                continue
            anchor = joint.parent_point if p == -1 else x[p] + R[p] @ joint.parent_point
            x[i] = anchor - R[i] @ joint.child_point
        return SE3.from_rotation_translation(R, jnp.stack(x))

    @eqx.filter_jit
    def momentum(self, g, angular_velocity, base_velocity=None) -> Float[Array, "N 6"]:
        """The momenta `m` `(N, 6)` of bodies at poses `g` turning at the world-frame
        angular velocities `(N, 3)`, each centre of mass moving with its joint (a floating
        root at `base_velocity`, default at rest), then projected onto the joints'
        velocity constraints (`project_momentum`: a hinge keeps only the turn about its
        axis)."""
        R, x = g[:, :3, :3], g[:, :3, 3]
        w = jnp.asarray(angular_velocity)
        v = [None] * self.n_bodies
        free = iter(
            jnp.zeros((self.n_bodies, 3))
            if base_velocity is None
            else jnp.atleast_2d(base_velocity)
        )
        for i in _depth_order(self.parents):
            p, joint = self.parents[i], self.joints[i]
            if joint is None:
                v[i] = next(free)
                continue
            anchor = 0.0 if p == -1 else v[p] + jnp.cross(w[p], R[p] @ joint.parent_point)
            v[i] = anchor - jnp.cross(w[i], R[i] @ joint.child_point)
        del x
        xi = jnp.concatenate(
            [jnp.einsum("nji,nj->ni", R, w), jnp.einsum("nji,nj->ni", R, jnp.stack(v))], axis=1
        )
        return self.project_momentum(g, self.legendre(xi))

    # ---- checks ---------------------------------------------------------------------------

    def joint_defect(self, g) -> Scalar:
        """`max |Φ(g)| / ℓ`: how far the joints are from holding, relative to the link
        length."""
        if self.n_constraints == 0:
            return jnp.zeros((), jnp.result_type(g, float))
        return jnp.max(jnp.abs(self.constraints(g))) / self.length_scale()

    def joint_tolerance(self, dtype) -> float:
        """The joint defect a state may start with: `√ε` of its dtype (a state assembled
        by `place` has a defect of a few ulps)."""
        return float(np.sqrt(np.finfo(dtype).eps))

    def check_element(self, name: str, g) -> None:
        """The bodies' poses (`AbstractLieSystem.check_element`), then the joints: a
        `ValueError` naming the first joint whose points do not coincide."""
        super().check_element(name, g)
        if not is_concrete(g) or self.n_constraints == 0:
            return
        g = jnp.asarray(g, jnp.result_type(g, float))
        bound = self.joint_tolerance(g.dtype)
        length = float(self.length_scale())
        world = jnp.eye(4, dtype=g.dtype)
        for i, (p, joint) in enumerate(zip(self.parents, self.joints)):
            if joint is None:
                continue
            defect = float(
                jnp.max(jnp.abs(joint.residual(world if p == -1 else g[p], g[i], length)))
            )
            if defect > bound * length:
                parent = "the world" if p == -1 else f"body {p}"
                raise ValueError(
                    f"`{name}` does not satisfy `joints[{i}]` ({joint.describe()} of body {i} "
                    f"to {parent}): its points are {defect:.3g} apart (link length "
                    f"{length:.3g}). Build the poses with `ArticulatedBodies.place`, or "
                    "check the joint points against the poses."
                )

    def element_valid(self, g):
        return super().element_valid(g) & (
            self.joint_defect(g) <= self.joint_tolerance(jnp.result_type(g, float))
        )
