"""Training: the PPO loop (`Trainer`), its rollouts and updates, and the runs built on it
(`mat train`: a run in its directory, seed sets, tuning, fine-tuning)."""
