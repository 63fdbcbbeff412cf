"""wbc_jax: batched whole-body control of legged manipulators in MuJoCo MJX."""

__version__ = "0.1.0"
