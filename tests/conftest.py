import jax

# Numerical tests run in float64 (float32 tests ask for it explicitly), with strict
# dtype promotion so that an accidental float32 constant cannot hide in a float64 run.
jax.config.update("jax_enable_x64", True)
jax.config.update("jax_numpy_dtype_promotion", "standard")
