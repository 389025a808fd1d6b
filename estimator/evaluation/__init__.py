"""Scoring a run: trajectory errors, consistency (NEES), image-only references, plots."""
