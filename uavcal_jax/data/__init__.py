"""Readers for real recordings (EuRoC ASL, TUM, ROS bags) and training windows."""
