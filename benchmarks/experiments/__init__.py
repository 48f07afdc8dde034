"""Experiments: scripts that train models, score recipes and reproduce the shipped weights."""
