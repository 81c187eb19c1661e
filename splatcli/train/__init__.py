"""Training: the loop, its config, state and checkpoints, data, first Gaussians, loss and log."""
