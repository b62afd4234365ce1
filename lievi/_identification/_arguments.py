"""The arguments of `fit_system` / `fit_inertia`, checked up front: each bad input is a
`ValueError` that names the argument."""

from __future__ import annotations

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

from .._checks import check_finite, is_concrete, membership_tolerance
from .._groups._conversions import quaternion_wxyz_to_matrix, quaternion_xyzw_to_matrix
from .._systems._base import AbstractLieSystem
from .._systems._rigid_body import RigidBody
from ._parametrisation import Free, inertia_parametrisation

QUATERNION_ORDERS = {"wxyz": quaternion_wxyz_to_matrix, "xyzw": quaternion_xyzw_to_matrix}


def orientations_from(orientations, quaternion):
    """Rotation matrices from the observed `orientations`: given as matrices, or as
    quaternions of the order `quaternion` names."""
    if quaternion is not None:
        if quaternion not in QUATERNION_ORDERS:
            raise ValueError(
                f"`quaternion` must be None, 'wxyz' (scalar first) or 'xyzw' (scalar last), "
                f"got {quaternion!r}."
            )
        if orientations is None or jnp.shape(orientations)[-1:] != (4,):
            shape = None if orientations is None else tuple(jnp.shape(orientations))
            raise ValueError(
                f"`quaternion={quaternion!r}`: `orientations` must be quaternions, shape "
                f"(*batch, S, 4), got {shape}."
            )
        check_finite("orientations", orientations)
        return QUATERNION_ORDERS[quaternion](orientations)
    if orientations is not None and jnp.ndim(orientations) >= 2:
        if jnp.shape(orientations)[-1] == 4 and jnp.shape(orientations)[-2] != 4:
            raise ValueError(
                f"`orientations` of shape {tuple(jnp.shape(orientations))}: these look like "
                "quaternions; convert with `lievi.quaternion_xyzw_to_matrix` (scalar last) or "
                "`lievi.quaternion_wxyz_to_matrix` (scalar first), or pass "
                "`quaternion='xyzw'` / `quaternion='wxyz'` to say which order they are in."
            )
    return orientations


def check_options(
    *, system, sample_every, max_iters, check_every, optimizer, learning_rate, gtol,
    identifiability_rtol, h, system_axis,
):  # fmt: skip
    """The scalar options."""
    if not isinstance(system, AbstractLieSystem):
        raise ValueError(
            f"`system` must be a lievi system (e.g. lievi.RigidBody), got {type(system).__name__}."
        )
    for name, value, low in (("sample_every", sample_every, 1), ("max_iters", max_iters, 1)):
        if not _is_int(value) or value < low:
            raise ValueError(f"`{name}` must be an integer ≥ {low}, got {value!r}.")
    if check_every is not None and (not _is_int(check_every) or check_every < 1):
        raise ValueError(f"`check_every` must be None or an integer ≥ 1, got {check_every!r}.")
    if isinstance(optimizer, str) and optimizer not in ("lbfgs", "adam"):
        raise ValueError(
            f"`optimizer` must be 'lbfgs', 'adam' or an optax transformation, got {optimizer!r}."
        )
    for name, value in (
        ("learning_rate", learning_rate),
        ("gtol", gtol),
        ("identifiability_rtol", identifiability_rtol),
    ):
        if value is None:
            continue
        if jnp.ndim(value) != 0 or not is_concrete(value) or not np.isfinite(float(value)):
            raise ValueError(f"`{name}` must be a finite Python number, got {value!r}.")
        if float(value) < 0 or (name != "gtol" and float(value) == 0):
            raise ValueError(
                f"`{name}` must be {'≥' if name == 'gtol' else '>'} 0, got {float(value)}."
            )
    if jnp.ndim(h) != 0:
        raise ValueError(f"`h` must be a scalar step size, got shape {jnp.shape(h)}.")
    if is_concrete(h):
        check_finite("h", h)
        if not float(h) > 0:
            raise ValueError(f"`h` must be > 0, got {float(h)}; pass a positive step size.")
    if system_axis not in (None, 0):
        raise ValueError(f"`system_axis` must be None or 0, got {system_axis!r}.")


def batch_shape_of(
    orientations, angular_velocities, element_ndim: int = 2, momentum_ndim: int = 1
) -> tuple[int, ...]:
    """The leading batch axes of the observations: orientations `(S, *element_shape)` per
    run, velocities `(S, *momentum_shape)` — `(S, n, n)` and `(S, d)` for one body (the
    defaults), one row per body after `S` for a system of several (`element_ndim`,
    `momentum_ndim`: the lengths of the system's shapes)."""
    if orientations is None and angular_velocities is None:
        raise ValueError("Give `orientations` and/or `angular_velocities` to fit to.")
    obs = orientations if orientations is not None else angular_velocities
    core = 1 + (element_ndim if orientations is not None else momentum_ndim)
    if jnp.ndim(obs) < core:
        name = "orientations" if orientations is not None else "angular_velocities"
        raise ValueError(f"`{name}` must have at least {core} axes, got {jnp.shape(obs)}.")
    return tuple(jnp.shape(obs)[: jnp.ndim(obs) - core])


def check_data(
    system, orientations, angular_velocities, m0, g0, trace, orientation_weight, velocity_weight
):
    """The observations, the given initial state, the gauge and the weights, broadcast to
    the batch. One run's state has the system's shapes (`element_shape()`,
    `momentum_shape()`: one body's `(n, n)` and `(d,)`, or a row per body for a system of
    several), so the batch axes are those in front of them and of the sample axis.
    **Returns:** `(batch_shape, n_samples, m0, g0, trace, weights)`."""
    if g0 is None and orientations is None:
        raise ValueError("`g0` is needed when no `orientations` are observed.")
    group = system.group
    element, momentum = tuple(system.element_shape()), tuple(system.momentum_shape())
    batch_shape = batch_shape_of(orientations, angular_velocities, len(element), len(momentum))
    obs = orientations if orientations is not None else angular_velocities
    n_samples = jnp.shape(obs)[len(batch_shape)]
    if n_samples < 2:
        raise ValueError(f"need at least 2 samples per body, got {n_samples}.")
    if orientations is not None:
        check_trailing("orientations", orientations, batch_shape, (n_samples, *element))
        check_rotations("orientations", orientations, group)
    if angular_velocities is not None:
        check_trailing(
            "angular_velocities", angular_velocities, batch_shape, (n_samples, *momentum)
        )
    if g0 is None and element != (3, 3):
        raise ValueError(
            f"Fitting `g0` is implemented on SO(3) for one body; give `g0` (shape {element}) "
            "for other groups and for systems of several bodies."
        )
    m0 = None if m0 is None else batched("m0", m0, batch_shape, momentum)
    g0 = None if g0 is None else batched("g0", g0, batch_shape, element)
    if m0 is not None:
        check_finite("m0", m0)
    if g0 is not None:
        check_finite("g0", g0)
        check_rotations("g0", g0, group)
    trace = None if trace is None else batched("trace", trace, batch_shape, ())
    if trace is not None:
        check_finite("trace", trace)
        if is_concrete(trace) and np.any(np.asarray(trace) <= 0):
            raise ValueError(f"`trace` (the gauge) must be > 0, got {np.asarray(trace)}.")
    weights = []
    for name, w in (
        ("orientation_weight", orientation_weight),
        ("velocity_weight", velocity_weight),
    ):
        w = jnp.broadcast_to(w, (n_samples,)) if jnp.ndim(w) == 0 else w
        w = batched(name, w, batch_shape, (n_samples,))
        check_finite(name, w)
        if is_concrete(w) and np.any(np.asarray(w) < 0):
            raise ValueError(f"`{name}` must be ≥ 0.")
        weights.append(w)
    return batch_shape, int(n_samples), m0, g0, trace, tuple(weights)


def fitted_leaves(system, params, batch_shape, system_axis, realisable) -> tuple:
    """The parametrisation of every leaf that `params` selects (a rigid body's inertia
    constrained, every other leaf free)."""
    indices = selected_indices(system, params)
    leaves = jax.tree.leaves(system)
    inertia_index = None
    if isinstance(system, RigidBody):
        inertia_index = selected_indices(system, lambda s: s.inertia, "inertia")[0]
    fitted = []
    for i in indices:
        value = leaves[i]
        if not is_concrete(value):
            raise ValueError(
                "The fitted parameters' initial guesses must be concrete arrays, not traced."
            )
        if not eqx.is_array_like(value) or not np.isrealobj(np.asarray(value)):
            raise ValueError(
                f"`params` selected a leaf that is not a real array: {type(value).__name__}."
            )
        value = np.asarray(value, float)
        core = value.shape[len(batch_shape) :] if system_axis == 0 else value.shape
        if system_axis == 0 and value.shape[: len(batch_shape)] != batch_shape:
            raise ValueError(
                f"with `system_axis=0` every fitted leaf must carry the batch axes {batch_shape} "
                f"first, got shape {value.shape}."
            )
        check_finite("params", value)
        if i == inertia_index:
            fitted.append(inertia_parametrisation(i, tuple(core), realisable))
        else:
            fitted.append(Free(i, tuple(core)))
    if realisable and not any(f.is_inertia for f in fitted):
        raise ValueError(
            "`realisable=True` constrains the inertia, which is not among the fitted `params`."
        )
    return tuple(fitted)


def check_horizons(horizons, n_samples) -> tuple[int, ...]:
    """The horizon stages: default 4, 8, 16, … up to `n_samples`."""
    if horizons is None:
        horizons = tuple(
            min(4 * 2**i, n_samples)
            for i in range(int(np.ceil(np.log2(max(n_samples / 4, 1)))) + 1)
        )
    horizons = tuple(int(x) for x in horizons)
    if (
        not horizons
        or horizons[-1] != n_samples
        or any(b <= a for a, b in zip(horizons, horizons[1:]))
        or horizons[0] < 2
    ):
        raise ValueError(
            f"`horizons` must increase from ≥ 2 to the number of samples ({n_samples}), "
            f"got {horizons}."
        )
    return horizons


class Marker:
    """Stands in for leaf `index` of a system while a `where` function is applied."""

    def __init__(self, index):
        self.index = index


def selected_indices(system, where, what="params") -> tuple[int, ...]:
    """Flat leaf indices of `system` that `where(system)` selects (no repeats)."""
    leaves, treedef = jax.tree.flatten(system)
    marked = jax.tree.unflatten(treedef, [Marker(i) for i in range(len(leaves))])
    try:
        chosen = where(marked)
    except Exception as error:
        raise ValueError(f"`{what}` could not be applied to the system: {error}") from error
    chosen = jax.tree.leaves(chosen, is_leaf=lambda x: isinstance(x, Marker))
    if not chosen or not all(isinstance(x, Marker) for x in chosen):
        raise ValueError(
            f"`{what}` must return leaves of the system (arrays, e.g. `lambda s: s.inertia` or "
            "`lambda s: (s.inertia, s.potential.center_of_mass)`), and at least one."
        )
    indices = tuple(x.index for x in chosen)
    if len(set(indices)) != len(indices):
        raise ValueError(f"`{what}` selects a leaf twice.")
    return indices


def check_trailing(name, x, batch_shape, core):
    if tuple(jnp.shape(x)) != tuple(batch_shape) + tuple(core):
        raise ValueError(
            f"`{name}` must have shape {tuple(batch_shape) + tuple(core)} (batch axes, then "
            f"{core}), got {tuple(jnp.shape(x))}."
        )
    check_finite(name, x)


def check_rotations(name, x, group):
    """Every `(n, n)` matrix of `x` in the group (orthogonal, det +1) to 1e-6 (float64)."""
    if not is_concrete(x):
        return
    x = np.asarray(x)
    tol = membership_tolerance(x.dtype)
    with jax.ensure_compile_time_eval():
        defect = np.asarray(group.membership_defect(jnp.asarray(x, float)))
    if np.any(defect > tol):
        worst = np.unravel_index(np.argmax(defect), defect.shape)
        raise ValueError(
            f"`{name}` must hold rotation matrices (orthogonal, det +1); entry "
            f"{tuple(int(i) for i in worst)} has membership defect {float(defect.max()):.3g} > "
            f"{tol:.1g}. Orthonormalise with a QR or polar decomposition, or build them with "
            "lievi.SO3.exp(rotation_vectors)."
        )


def batched(name, x, batch_shape, core):
    """Broadcast a shared or per-body argument to `batch_shape + core`."""
    shape = tuple(jnp.shape(x))
    if shape == tuple(core):
        return jnp.broadcast_to(x, tuple(batch_shape) + tuple(core)) if batch_shape else x
    if shape == tuple(batch_shape) + tuple(core):
        return x
    raise ValueError(
        f"`{name}` must have shape {tuple(core)} (shared) or {tuple(batch_shape) + tuple(core)} "
        f"(one per body), got {shape}."
    )


def _is_int(value):
    return not isinstance(value, bool) and isinstance(value, (int, np.integer))
