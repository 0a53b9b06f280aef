"""Model-based trajectory tracking (PI outer loop, backstepping inner loop) and baselines, as a companion."""
