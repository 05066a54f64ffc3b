"""Validation and benchmark code: the comparisons behind docs/VALIDATION.md."""
