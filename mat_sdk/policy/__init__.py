"""What a trained policy is: the networks, the algorithm registry, the training config, the
checkpoint file, the running normalisers and the one-call control-step graph."""
