"""Runs: what a training launch is and leaves on disk, one job per module."""
