"""JAX runtime: its configuration (precision, compilation cache) and the compiled-program cache."""
