"""Training: one `train()`, its config and presets, the run folder and log, checkpoints, validation."""
