"""The paper's metrics: per-step integrands and the per-run finalization."""
