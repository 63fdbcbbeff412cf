"""The physics backend adapter (MJX JAX / MuJoCo Warp), contacts, observation, clearance."""
