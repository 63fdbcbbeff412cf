"""``python -m wbc_jax``: the ``wbc-jax`` console script."""

from wbc_jax.cli import run

if __name__ == "__main__":
    run()
