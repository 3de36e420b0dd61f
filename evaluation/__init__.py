"""Evaluation: VLN-CE metrics (and, later, the experiment runner)."""
