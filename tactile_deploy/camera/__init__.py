"""Synthetic cameras of the simulator."""
