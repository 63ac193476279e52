"""Reporting: the test report and its provenance, tables, figures and the studies' statistics."""
