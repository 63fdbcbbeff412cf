"""Studies a user runs: spec files, the factorial campaign, regression, gain tuning, the trot study, the demo."""
