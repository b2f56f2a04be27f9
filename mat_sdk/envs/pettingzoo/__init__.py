"""PettingZoo both ways: any PettingZoo env as a team (`from_pettingzoo`), and a team as a
PettingZoo `ParallelEnv`."""
