"""Argument checks that raise `ValueError` naming the argument and the fix.

Checks on *values* (positivity, orthogonality, NaN) raise only when the value is
concrete, i.e. when the function is called eagerly. Under `jit`/`vmap`/`grad` the values
are tracers; there the same checks run inside the computation (`input_valid`) and a bad
value gives `RESULTS.invalid_input` for that body — never a silent number.

A parameter check is written once, as a *condition*: a traceable boolean array and the
message that names the parameter (`Conditions`). `raise_if_violated` is its eager form
(a concrete `False` raises the message) and `all_hold` its traced form (`input_valid`).
"""

from __future__ import annotations

import contextlib

import equinox as eqx
import jax
import jax.numpy as jnp
import numpy as np

# `(holds, message)`: a traceable boolean array and the `ValueError` message if it fails.
Conditions = list[tuple[jax.Array, str]]


def is_concrete(*xs) -> bool:
    """Whether every `x` has a value this process can read: not a tracer, and not a global
    array spread over several processes (`jax.distributed`), whose rows live elsewhere;
    for both, the same checks run inside the computation."""
    return not any(
        isinstance(x, jax.core.Tracer) or (isinstance(x, jax.Array) and not x.is_fully_addressable)
        for x in xs
    )


def abstract_key(tree):
    """`tree` as a trace of it sees it: its structure, its leaves that are not arrays, and
    its arrays' shapes and dtypes. Hashable where the structure and those leaves are: the
    cache key of an answer computed from shapes alone (`abstract_tree` rebuilds the tree,
    its arrays as `jax.ShapeDtypeStruct`s). Plain tuples, built in a few µs for a state of
    20 arrays: it runs at every eager call."""
    leaves, treedef = jax.tree.flatten(tree)
    return treedef, tuple(_abstract(x) if eqx.is_array(x) else (x,) for x in leaves)


def _abstract(x):
    """`(shape, dtype, weak_type)` of an array."""
    if isinstance(x, jax.Array):
        return x.shape, x.dtype, x.weak_type
    return np.shape(x), np.result_type(x), False


def abstract_tree(key):
    """The tree of `abstract_key`, its arrays as `jax.ShapeDtypeStruct`s."""
    treedef, leaves = key
    return jax.tree.unflatten(
        treedef,
        [x[0] if len(x) == 1 else jax.ShapeDtypeStruct(x[0], x[1], weak_type=x[2]) for x in leaves],
    )


def tracing() -> bool:
    """Whether a JAX transformation (`jit`, `vmap`, `grad`, a loop's body) is tracing the
    caller: JAX's own test, private, hence guarded (without it, assume so: the traced
    path is always correct, only slower to compile per horizon)."""
    try:
        from jax._src.core import trace_state_clean
    except ImportError:
        return True
    return not trace_state_clean()


def evaluated_now():
    """A context in which a jit-compiled check on concrete arrays runs now and returns
    concrete values, also inside an outer `jit` that captured the arrays from outside.
    Outside any transformation it is a plain call: `jax.ensure_compile_time_eval` there
    would also run the check's constant-only operations one small program at a time."""
    return jax.ensure_compile_time_eval() if tracing() else contextlib.nullcontext()


def check_shape(name: str, x, shape: tuple[int, ...], what: str = "") -> None:
    if tuple(jnp.shape(x)) != tuple(shape):
        hint = f" ({what})" if what else ""
        raise ValueError(
            f"`{name}` must have shape {tuple(shape)}{hint}, got {tuple(jnp.shape(x))}."
        )


def check_finite(name: str, x) -> None:
    if is_concrete(x) and not np.all(np.isfinite(np.asarray(x))):
        raise ValueError(f"`{name}` contains NaN or inf; pass finite values.")


def spd_conditions(name: str, matrix) -> Conditions:
    """`matrix` (`(k, k)`) finite, symmetric to 1e-10 relative and positive definite, as
    conditions (traceable; `check_spd` raises on them eagerly)."""
    m = jnp.asarray(matrix)
    m = m.astype(jnp.result_type(m, float))
    finite = jnp.all(jnp.isfinite(m))
    m = jnp.where(finite, m, jnp.eye(m.shape[-1], dtype=m.dtype))
    transpose = jnp.swapaxes(m, -1, -2)
    symmetric = jnp.all(jnp.abs(m - transpose) <= 1e-10 * jnp.max(jnp.abs(m)))
    positive = _positive_definite((m + transpose) / 2)
    return [
        (finite, f"`{name}` contains NaN or inf; pass finite values."),
        (symmetric, f"`{name}` must be symmetric; symmetrise it as (M + Mᵀ)/2."),
        (positive, f"`{name}` must be positive definite (all eigenvalues > 0)."),
    ]


def _positive_definite(m):
    """Whether the symmetric `m` `(…, k, k)` is positive definite: the pivots of Gaussian
    elimination without pivoting all positive (Sylvester: the pivots are the ratios of
    the leading principal minors), for `k ≤ 8` — elementwise arithmetic, so a batch of
    any size runs where the state runs (a GPU's batched eigensolver refuses batches of
    1e7 matrices); `eigvalsh` above that. The elimination is a `lax.fori_loop` over the
    columns, compiled once: unrolled, each of its `k(k − 1)/2` divisions was a fused loop
    of its own, and the 6×6 check of `lievi.RigidBodySE3` compiled for about a second
    (2-core CPU), most of the difference between its first call and `lievi.RigidBody`'s."""
    k = m.shape[-1]
    if k > 8:
        return jnp.min(jnp.linalg.eigvalsh(m)) > 0
    index = np.arange(k)

    def eliminate(j, carry):
        a, ok = carry
        column = jax.lax.dynamic_index_in_dim(a, j, axis=-1, keepdims=False)
        pivot = jax.lax.dynamic_index_in_dim(column, j, axis=-1, keepdims=False)
        # A non-positive pivot has already failed; NaN past it compares false.
        ok = ok & (pivot > 0)
        # The Schur complement of the pivot in the trailing block (`m` is symmetric: its
        # row `j` is its column `j`).
        below = jnp.where(index > j, column, 0)
        return a - below[..., :, None] * below[..., None, :] / pivot[..., None, None], ok

    ok = jnp.ones(m.shape[:-2], bool)
    return jnp.all(jax.lax.fori_loop(0, k, eliminate, (m, ok))[1])


def check_spd(name: str, matrix) -> None:
    """Symmetric positive definite (`spd_conditions`), for a concrete (k, k) array (the
    dtype is checked for traced arrays too; their values are checked by `input_valid`)."""
    check_real_dtype(name, matrix)
    raise_if_violated(spd_conditions, name, matrix)


def finite_conditions(tree, name: str | None = None) -> Conditions:
    """Every floating-point array of `tree` finite, one condition per array, named by its
    field (or `name`)."""
    conditions = []
    for path, leaf in jax.tree_util.tree_leaves_with_path(tree):
        if eqx.is_inexact_array(leaf):
            keys = [
                k.name if isinstance(k, jax.tree_util.GetAttrKey) else k.key
                for k in path
                if isinstance(k, (jax.tree_util.GetAttrKey, jax.tree_util.DictKey))
            ]
            label = keys[-1] if keys else name or "parameter"
            message = f"`{label}` contains NaN or inf; pass finite values."
            conditions.append((jnp.all(jnp.isfinite(leaf)), message))
    return conditions


def shown(x, template: str) -> str:
    """`template.format(value of x)` where `x` is concrete, else `""`: a condition's
    message may show the offending value. `raise_if_violated` builds the messages it
    raises from concrete values; traced (`all_hold`), the messages are never read."""
    if not is_concrete(x):
        return ""
    value = np.asarray(x)
    return template.format(value.tolist() if value.ndim else value.item())


def all_hold(conditions: Conditions):
    """The traced form of a list of conditions: one boolean array."""
    valid = jnp.asarray(True)
    for holds, _ in conditions:
        valid = valid & jnp.all(holds)
    return valid


def raise_if_violated(conditions, *args) -> None:
    """The eager form of `conditions(*args)` (e.g. a module's bound `parameter_conditions`,
    whose module is part of it): when every array in them is concrete, evaluate the
    conditions now — also inside an outer `jit` — and raise the first failed condition's
    message. Traced values are left to `all_hold`.

    The conditions are evaluated as one compiled program (`_holds`): operation by
    operation, each operation would be a small program compiled at its first call (about
    half a second of a first `RigidBodySE3(…)` on the 2-core reference machine). Python
    floats among the values are passed as arrays, so that a new value is not a new
    program. The messages are read only when a condition fails."""
    conditions, args = jax.tree.map(_float_as_array, (conditions, args))
    if not is_concrete(*[x for x in jax.tree.leaves((conditions, args)) if eqx.is_array(x)]):
        return
    with evaluated_now():
        if bool(_holds(conditions, *args)):
            return
    with jax.ensure_compile_time_eval():
        for holds, message in conditions(*args):
            if not bool(jnp.all(holds)):
                raise ValueError(message)


def _float_as_array(x):
    return jnp.asarray(x) if type(x) is float else x


@eqx.filter_jit
def _holds(conditions, *args):
    return all_hold(conditions(*args))


def membership_tolerance(dtype) -> float:
    """The one bound on a group element's membership defect (`membership_defect`, e.g.
    `‖gᵀg − I‖_F + |det g − 1|`), eager and traced: 1e-6, or 64 ulps of `dtype` where
    that is larger (float32: 7.6e-6)."""
    return max(1e-6, 64 * float(jnp.finfo(jnp.result_type(dtype, float)).eps))


def drifts_off_group(dtype) -> bool:
    """Whether a long run in `dtype` can drift out of `membership_tolerance`: products of
    group elements add an ulp of defect each, a random walk `~√N ε` that passes 64 ulps
    within a few thousand float32 steps (float64 would need ~1e19). Such runs keep `g`
    on the group (`MatrixLieGroup.project`) wherever they save it."""
    return float(jnp.finfo(jnp.result_type(dtype, float)).eps) > 1e-10


def check_scalar(name: str, x, *, positive: bool = False) -> None:
    """Reject strings, bools, complex and non-scalar values; concrete values must be
    finite (and, with `positive`, a normal number > 0)."""
    if isinstance(x, (str, bytes)) or isinstance(x, (bool, np.bool_)):
        raise ValueError(f"`{name}` must be a real number, got {x!r}.")
    dtype = jnp.result_type(x)
    if not (jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)):
        raise ValueError(f"`{name}` must be a real number, got dtype {dtype}.")
    if jnp.ndim(x) != 0:
        raise ValueError(f"`{name}` must be a scalar, got shape {jnp.shape(x)}.")
    if is_concrete(x):
        check_finite(name, x)
        if positive:
            value = float(x)
            tiny = float(jnp.finfo(jnp.result_type(x, float)).tiny)
            if not value > 0:
                raise ValueError(f"`{name}` must be > 0, got {value}; pass a positive step size.")
            if value < tiny:
                raise ValueError(
                    f"`{name}` = {value} is subnormal (below {tiny:.3g}); pass a normal "
                    "positive step size."
                )


def check_real_dtype(name: str, x) -> None:
    """Reject complex, bool and non-numeric arrays (they would be cast silently)."""
    if isinstance(x, (str, bytes)):
        dtype = None
    else:
        dtype = np.asarray(x).dtype if isinstance(x, (list, tuple)) else jnp.result_type(x)
    if dtype is None or not (
        jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)
    ):
        raise ValueError(
            f"`{name}` must hold real numbers, got {'a string' if dtype is None else dtype}."
        )


def step_size_valid(h):
    """Traceable: `h` is a finite normal number > 0 (per body)."""
    tiny = jnp.finfo(jnp.result_type(h, float)).tiny
    return jnp.isfinite(h) & (h >= tiny)


def input_valid(system, g0, m0, h, t0=0.0, parameters: bool = True):
    """Traceable validity of a run's inputs: the system's parameters (unless
    `parameters=False`: checked already), `g0` in the group, finite `m0`, `t0`, and a
    positive normal `h`. A boolean array (a run turns `False` into
    `RESULTS.invalid_input`; it is computed inside the run's own program)."""
    return (
        (system.parameters_valid() if parameters else True)
        & system.element_valid(g0)
        & jnp.all(jnp.isfinite(m0))
        & step_size_valid(h)
        & jnp.isfinite(t0)
    )


def as_int(value):
    """NumPy integers become Python ints (a static field must not hold a NumPy scalar)."""
    return int(value) if isinstance(value, np.integer) else value


def check_integer(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < minimum:
        raise ValueError(f"`{name}` must be an integer ≥ {minimum}, got {value!r}.")
    return int(value)


def state_dtype(system, *arrays):
    """The dtype a run computes in: NumPy promotion of the state, `h` and the system's
    floating-point parameters (a float64 inertia with a float32 state runs in float64;
    for float32 throughout, pass float32 parameters too)."""
    params = [x for x in jax.tree.leaves(system) if eqx.is_inexact_array(x)]
    return jnp.result_type(*arrays, *params, float)
