"""The robot: MJCF scene loading, static ids, the batched object model."""
