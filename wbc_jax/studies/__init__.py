"""Studies built on the rollout: demo, trot, gain tuning."""
