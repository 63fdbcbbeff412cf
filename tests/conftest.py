"""Shared pytest configuration: persistent JAX compile cache, float32 by default."""

from wbc_jax.sim import jaxcfg

jaxcfg.configure()
