"""Synthetic range scenes with ground truth (being written)."""
