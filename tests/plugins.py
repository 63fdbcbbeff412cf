"""Controller plug-ins for tests/test_plugin.py (imported as ``tests.plugins`` from the repository root)."""

from dataclasses import dataclass

from wbc_jax.rollout.controllers import CentroidalController, TransportController


@dataclass(frozen=True, eq=False)
class Same(TransportController):
    """The transport controller unchanged, from outside the package."""


@dataclass(frozen=True)
class ByIdentity(TransportController):
    """Compared by its generated dataclass equality, not by value: refused."""


@dataclass(frozen=True, eq=False)
class NoDefault(TransportController):
    """A field without a default: refused."""

    gain: float = None  # a default of a type a spec cannot set


@dataclass(frozen=True, eq=False)
class SameTrot(CentroidalController):
    """The centroidal controller unchanged, from outside the package."""


@dataclass(frozen=True, eq=False)
class NoParams(TransportController):
    """A float field, but no with_params: a spec cannot vary it."""

    gain: float = 1.0


@dataclass(frozen=True, eq=False)
class TakenColumn(TransportController):
    """Claims a column the results table already has: refused."""

    extra_columns = ("R",)
