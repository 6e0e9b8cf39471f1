"""Recorded runs: reading a bag back (RunData) and the report of one run (figures, report.md)."""
