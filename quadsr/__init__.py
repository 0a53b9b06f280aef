"""quadsr: symbolic-regression models and model-based control of quadrotors over MAVLink."""

__version__ = "0.1.0"
