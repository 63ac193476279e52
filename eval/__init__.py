"""Evaluation: test protocol, per-step records, metrics, tables, plots."""
