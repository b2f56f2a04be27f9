"""Foundations every layer may use: atomic files and locks, worker processes, timing."""
