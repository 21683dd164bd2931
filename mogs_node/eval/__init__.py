"""Evaluation: depth, trajectory and rendering metrics, and the `mogs eval` commands."""
