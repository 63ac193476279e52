"""Data: the Town03-like SUMO network, demand, static objects and scenario files (no code)."""
