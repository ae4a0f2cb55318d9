"""Evaluation against ground truth and against COLMAP: metrics, alignment, comparison runs and reports."""
