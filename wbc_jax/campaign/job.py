"""A campaign being run: its spec, batch and output (:class:`Job`) and what it has left so far (:class:`Status`)."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import jax

from wbc_jax.campaign.build import LOG_EVERY, Built
from wbc_jax.campaign.spec import Spec


def chunk_seconds(built: Built) -> float:
    """Simulated seconds per chunk of ``built`` (its logged samples per chunk x LOG_EVERY control periods) [s]."""
    return built.logs_per_chunk * LOG_EVERY * built.sim.dt_control


@dataclass
class Status:
    """What a running campaign has left so far (process 0), for the line of an interrupt: the stage (setup,
    chunks, written: results.csv and manifest.json are in DIR), the checkpoint and the chunks it holds."""

    out: str
    ckpt: Path | None = None
    stage: str = "setup"
    saved: int = 0
    n_chunks: int = 0
    writer: bool = True

    def describe(self) -> str:
        if not self.writer:
            return f"in process {jax.process_index()} (process 0 says what it kept)"
        if self.stage == "written":
            return (f"during the report; {self.out}/results.csv and manifest.json are written; write the report "
                    f"with wbc-jax report {self.out}/results.csv --out {self.out}/report")
        if self.stage == "setup":
            return (f"during setup; the checkpoint in {self.ckpt} ({self.saved} of {self.n_chunks} chunks) is kept; "
                    "continue with --resume" if self.saved else "during setup; nothing written")
        if self.saved:
            return (f"after {self.saved} of {self.n_chunks} chunks; finished chunks kept in {self.ckpt}; continue "
                    "with --resume")
        return "before the first chunk finished; nothing written"


@dataclass
class Job:
    """One campaign being run: its spec, the built batch (placed on the devices), where process 0 writes.

    Attributes:
        spec: the validated spec (``--backend`` applied).
        built: :func:`wbc_jax.campaign.build.build` of it.
        batch: the Batch placed by ``spread``.
        spread: how the runs are spread over devices and processes (:mod:`wbc_jax.rollout.spread`).
        identity: :func:`wbc_jax.campaign.manifest.run_identity` of the run.
        gains: the gains given (None: the defaults).
        writer: this process writes (process 0).
        out: the output folder (process 0; None elsewhere).
        ckpt: the checkpoint folder (process 0; None elsewhere).
        status: what the run has left so far (for an interrupt's line).
    """

    spec: Spec
    built: Built
    batch: object
    spread: object
    identity: dict
    gains: object
    writer: bool
    out: Path | None
    ckpt: Path | None
    status: Status

    @property
    def chunk_s(self) -> float:
        """Simulated seconds per chunk."""
        return chunk_seconds(self.built)

    @property
    def seconds(self) -> float:
        """Simulated seconds in all."""
        return self.built.n_chunks * self.chunk_s
