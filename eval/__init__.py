"""Evaluation, the layer over cosim and agents, by responsibility: cli/ (the `cosim` command),
scale/ (Ray, benchmark, PBT), training/, testing/, reporting/, and labels.py (the names and
colours every subpackage shows; docs/design.md#module-map)."""
