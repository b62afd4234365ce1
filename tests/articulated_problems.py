"""Test problems of articulated bodies, and an independent reference for them: the
continuous Newton–Euler equations with Lagrange multipliers in maximal coordinates,
index-reduced (the constraints differentiated twice), integrated by DOP853.

The reference writes its own joint equations, forces and kinematics (nothing from
`lievi` but the problem's numbers), so it checks the integrator's equations as well as
its order.
"""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

import lievi

GRAVITY = 9.81
E2, E1 = jnp.array([0.0, 1.0, 0.0]), jnp.array([1.0, 0.0, 0.0])


def _rod(mass, length, radius=0.05):
    """Principal moments of a solid cylinder along its third axis, about its centre."""
    side = mass * (3 * radius**2 + length**2) / 12
    return jnp.array([side, side, mass * radius**2 / 2])


def triple_pendulum(gravity=GRAVITY):
    """Three rods joined end to end by ball joints, the first to a pivot at the origin:
    `(system, g0, m0)`, the links tilted and spinning in 3-D."""
    masses = jnp.array([1.0, 0.8, 0.6])
    lengths = jnp.array([1.0, 0.8, 0.7])
    inertia = jnp.stack([_rod(m, ell, radius=0.2) for m, ell in zip(masses, lengths)])
    joints = [lievi.BallJoint(jnp.zeros(3), jnp.array([0.0, 0.0, lengths[0] / 2]))]
    for i in (1, 2):
        joints.append(
            lievi.BallJoint(
                jnp.array([0.0, 0.0, -lengths[i - 1] / 2]),
                jnp.array([0.0, 0.0, lengths[i] / 2]),
            )
        )
    system = lievi.ArticulatedBodies(inertia, masses, [-1, 0, 1], joints, gravity=gravity)
    R = lievi.SO3.exp(jnp.array([[0.6, 0.2, 0.0], [0.9, -0.4, 0.3], [-0.3, 1.1, -0.2]]))
    g0 = system.place(R)
    m0 = system.momentum(g0, jnp.array([[0.0, 0.5, 0.3], [0.8, 0.0, -0.4], [-0.3, 1.0, 0.5]]))
    return system, g0, m0


def hinge_chain(n=5, gravity=GRAVITY, fixed=True):
    """`n` rods joined by hinges whose axes alternate between the bodies' `e₂` and `e₁`,
    the first hinged to the world at the origin (`fixed`) or floating: `(system, g0, m0)`."""
    masses = jnp.linspace(1.0, 0.6, n)
    length = 0.6
    inertia = jnp.stack([_rod(m, length) for m in masses])
    axes = [E2 if i % 2 == 0 else E1 for i in range(n)]
    top, bottom = jnp.array([0.0, 0.0, length / 2]), jnp.array([0.0, 0.0, -length / 2])
    joints = [lievi.HingeJoint(jnp.zeros(3), top, axes[0]) if fixed else None]
    joints += [lievi.HingeJoint(bottom, top, axes[i]) for i in range(1, n)]
    parents = list(range(-1, n - 1))
    system = lievi.ArticulatedBodies(inertia, masses, parents, joints, gravity=gravity)
    angles = 0.5 * jnp.cos(jnp.arange(n) + 0.3)
    rates = 1.5 * jnp.sin(2.0 * jnp.arange(n) + 1.0)
    R, w = [], []
    for i in range(n):
        turn = lievi.SO3.exp(angles[i] * axes[i])
        R.append(turn if i == 0 else R[-1] @ turn)
        spin = rates[i] * (R[-1] @ axes[i])
        w.append(spin if i == 0 else w[-1] + spin)
    g0 = system.place(jnp.stack(R))
    base_velocity = None if fixed else jnp.array([0.3, -0.2, 0.1])
    m0 = system.momentum(g0, jnp.stack(w), base_velocity)
    return system, g0, m0


# ---- the joints' defects of a run ----------------------------------------------------------


@eqx.filter_jit
def velocity_defect(system, g, m):
    """`max |C(g) ξ|` relative to the speeds of the joint points, `ℓ|Ω| + |v|`, per state."""
    xi = jax.vmap(system.velocity)(m)
    speed = system.length_scale() * jnp.max(jnp.abs(xi[..., :3])) + jnp.max(jnp.abs(xi[..., 3:]))
    defect = jax.vmap(system.velocity_constraints)(g, m)
    return jnp.max(jnp.abs(defect)) / speed


@eqx.filter_jit
def joint_defects(system, g):
    """`max |Φ(g)| / ℓ` of each saved state."""
    return jax.vmap(system.joint_defect)(g)


# ---- the reference: Newton–Euler equations with multipliers, index-reduced -------------------


def _hat(v):
    return jnp.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


def _se3_hat(xi):
    top = jnp.concatenate([_hat(xi[:3]), xi[3:, None]], axis=1)
    return jnp.concatenate([top, jnp.zeros((1, 4))], axis=0)


def _joint_equations(joint, parent, child):
    """The joint's equations, written here from scratch: the points coincide; a hinge's
    child axis is perpendicular to two directions perpendicular to the parent's axis."""
    Rp, xp, Rc, xc = parent[:3, :3], parent[:3, 3], child[:3, :3], child[:3, 3]
    ball = xp + Rp @ joint.parent_point - xc - Rc @ joint.child_point
    if isinstance(joint, lievi.BallJoint):
        return ball
    n_p = joint.parent_axis / jnp.linalg.norm(joint.parent_axis)
    n_c = joint.axis / jnp.linalg.norm(joint.axis)
    # Any basis of the plane perpendicular to n_p spans the same equations.
    helper = jnp.array([0.3, 0.5, 0.8])
    u1 = jnp.cross(n_p, helper)
    u1 = u1 / jnp.linalg.norm(u1)
    u2 = jnp.cross(n_p, u1)
    return jnp.concatenate([ball, jnp.stack([(Rp @ u1) @ (Rc @ n_c), (Rp @ u2) @ (Rc @ n_c)])])


def reference_rhs(system):
    """`y ↦ ẏ` for `y` = each body's `(R (9), x (3), Ω (3), v (3))`, `v` the body-frame
    velocity of its centre of mass, `Ω` its body angular velocity."""
    n = system.n_bodies
    mass = np.asarray(system.mass)
    inertia = np.asarray(system.inertia)
    J = np.stack([np.diag(I) if I.ndim == 1 else I for I in inertia])
    gravity = float(system.potential.gravity) if system.potential is not None else 0.0

    def poses(y):
        y = y.reshape(n, 18)
        R = y[:, :9].reshape(n, 3, 3)
        g = jnp.zeros((n, 4, 4)).at[:, :3, :3].set(R).at[:, :3, 3].set(y[:, 9:12])
        return g.at[:, 3, 3].set(1.0), y[:, 12:15], y[:, 15:18]

    def phi(g):
        world = jnp.eye(4)
        return jnp.concatenate(
            [
                _joint_equations(joint, world if p == -1 else g[p], g[i])
                for i, (p, joint) in enumerate(zip(system.parents, system.joints))
                if joint is not None
            ]
        )

    def rhs(y):
        g, Om, v = poses(y)
        xi = jnp.concatenate([Om, v], axis=1)
        C = jax.jacfwd(lambda eta: phi(g + g @ jax.vmap(_se3_hat)(eta)))(jnp.zeros((n, 6)))
        C = C.reshape(C.shape[0], 6 * n)

        X = jax.vmap(_se3_hat)(xi)

        def along(t):
            # `exp(tX)` to second order: the same second derivative at t = 0, no `expm`.
            return phi(g @ (jnp.eye(4) + t * X + t**2 / 2 * X @ X))

        # d²/dt² Φ(g exp(tξ)) at t = 0: the velocity-quadratic term Ċξ.
        quadratic = jax.jvp(lambda s: jax.jvp(along, (s,), (1.0,))[1], (0.0,), (1.0,))[1]
        Pi = jnp.einsum("nij,nj->ni", J, Om)
        P = mass[:, None] * v
        f_world = jnp.zeros((n, 3)).at[:, 2].set(-mass * gravity)
        f_body = jnp.einsum("nji,nj->ni", g[:, :3, :3], f_world)
        # Euler–Poincaré on SE(3): Π̇ = Π×Ω + P×v + τ, Ṗ = P×Ω + f (body frame).
        rhs_m = jnp.concatenate([jnp.cross(Pi, Om) + jnp.cross(P, v), jnp.cross(P, Om) + f_body], 1)
        Mblock = jax.scipy.linalg.block_diag(
            *[jax.scipy.linalg.block_diag(J[i], mass[i] * np.eye(3)) for i in range(n)]
        )
        c = C.shape[0]
        kkt = jnp.block([[Mblock, -C.T], [C, jnp.zeros((c, c))]])
        sol = jnp.linalg.solve(kkt, jnp.concatenate([rhs_m.reshape(-1), -quadratic]))
        xi_dot = sol[: 6 * n].reshape(n, 6)
        R = g[:, :3, :3]
        R_dot = R @ jax.vmap(_hat)(Om)
        x_dot = jnp.einsum("nij,nj->ni", R, v)
        return jnp.concatenate([R_dot.reshape(n, 9), x_dot, xi_dot], axis=1).reshape(-1)

    return jax.jit(rhs)


def reference_state(system, g, m):
    """The reference's flat state of `(g, m)`."""
    xi = system.velocity(m)
    n = system.n_bodies
    return jnp.concatenate([g[:, :3, :3].reshape(n, 9), g[:, :3, 3], xi], axis=1).reshape(-1)


def reference_poses(system, y):
    """`(R, x)` of a reference state."""
    y = y.reshape(system.n_bodies, 18)
    return y[:, :9].reshape(-1, 3, 3), y[:, 9:12]


def satellite():
    """A floating base (a box) with two hinged panels, one on each side: a tree whose root
    has two children, spinning and deploying in free space. `(system, g0, m0)`."""
    inertia = jnp.array([[1.0, 1.2, 0.8], [0.02, 0.05, 0.07], [0.02, 0.05, 0.07]])
    masses = jnp.array([5.0, 0.5, 0.5])
    side = jnp.array([0.5, 0.0, 0.0])
    reach = jnp.array([0.6, 0.0, 0.0])
    joints = [
        None,
        lievi.HingeJoint(side, -reach, E2),
        lievi.HingeJoint(-side, reach, E2),
    ]
    system = lievi.ArticulatedBodies(inertia, masses, [-1, 0, 0], joints)
    base = lievi.SO3.exp(jnp.array([0.2, -0.1, 0.3]))
    angles, rates = jnp.array([0.4, -0.3]), jnp.array([0.5, -0.7])
    w_base = jnp.array([0.1, 0.2, 0.3])
    R = [base] + [base @ lievi.SO3.exp(a * E2) for a in angles]
    w = [w_base] + [w_base + r * (base @ E2) for r in rates]
    g0 = system.place(jnp.stack(R), base=jnp.array([1.0, 2.0, -0.5]))
    m0 = system.momentum(g0, jnp.stack(w), base_velocity=jnp.array([0.05, -0.02, 0.01]))
    return system, g0, m0
