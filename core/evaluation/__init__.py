"""Evaluation: metrics, the comparison harness and its report."""
