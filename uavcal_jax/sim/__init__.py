"""Flight simulator: trajectories, IMU synthesis, rendering, EuRoC ASL output."""
