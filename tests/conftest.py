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
