"""Measuring: the paper's verification, baselines, the accuracy benchmark and its sets, error measures, pictures."""
