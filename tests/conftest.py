import jax

# Numerical tests run in float64; float32 tests ask for float32 arrays explicitly.
jax.config.update("jax_enable_x64", True)


import pytest  # noqa: E402


@pytest.fixture(autouse=True, scope="module")
def _fresh_compilation_caches():
    """Drop JAX's compiled programs after each test module: the suite compiles several
    hundred XLA programs, and a long-lived process that keeps them all has crashed inside
    XLA's compiler (not reproducible in a fresh process)."""
    yield
    jax.clear_caches()


# The heavy cases of the default suite's checks carry `@pytest.mark.extended` (a whole test)
# or `pytest.param(..., marks=pytest.mark.extended)` (one case), with the seconds they took:
# most took ≥ 8 s on one worker of the 2-core reference machine (`pytest --durations`;
# mostly compiling SE(3), composition and coupled-body programs), so that the default suite
# stays near 10 minutes. They run with `pytest -m extended` (CI runs them after the default
# suite). Whatever they cost, the default suite keeps the paper's equivalence theorem, the
# Poisson property, the gradient and implicit-derivative checks against finite differences,
# one fast-against-reference parity case, the float32 batches and the two-process run.
