"""Baselines flown beside the model-based controller: a PX4-style PID cascade and an SE(3) geometric one."""
