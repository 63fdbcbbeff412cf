"""Campaigns: spec, design, runner with checkpoints, results, regress."""
