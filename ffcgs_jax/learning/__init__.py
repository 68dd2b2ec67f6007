"""The learned wrist-pose sampler: layers, the CVAE, its weights and checkpoints, its training data and
training loop."""
