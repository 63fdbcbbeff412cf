"""The package version (one place: the report, the manifests and ``wbc_jax.__version__`` read it)."""

__version__ = "0.1.0"
