"""Procedural and analytic scenes with exact ground truth."""
