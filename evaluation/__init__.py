"""Evaluation: VLN-CE metrics, the experiment runner, the paper's presets and the generated episode set.

``python -m evaluation run|preset|generate|summarize`` (see :mod:`evaluation.cli`).
"""
