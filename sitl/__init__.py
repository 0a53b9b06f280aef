"""The simulated quadrotor: physics, sensors, and the simulator side of PX4's MAVLink HIL interface."""
