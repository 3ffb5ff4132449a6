"""Mood Swings pipeline stages: one module per pipeline step (paper Fig. 1)."""
