"""Simulation engine: MJCF model, scenario batching, MJX physics, the chunked batched rollout, sharding, compiled-program cache."""
