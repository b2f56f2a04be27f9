"""The team interface every env family implements (`ArrayTeam`), its checks, faults,
vectorised stepping, a task's recipe, and the smallest team (a coordination game)."""
