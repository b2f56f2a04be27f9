"""Evaluation: a checkpoint's policy acting in episodes, the evaluation protocol during
training, robustness sweeps, velocity tracking and the report over seeds."""
