"""The batched closed-loop rollout: config, state, step, loop, batching, sharding, caches."""
