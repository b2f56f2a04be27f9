"""MuJoCo robots as teams of agents: models and their tasks, reward terms, observations from
hardware signals, actuation, randomization, and the robot families (ours, MaMuJoCo)."""
