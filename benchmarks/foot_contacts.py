"""How a legged policy walks: each foot's share of control steps on the floor, from the
robot's own contact signal, over one episode at a fixed command (the first second left out).

    PYTHONPATH=examples python -m benchmarks.foot_contacts runs/spot/seed_*/checkpoint.pt \\
        --command 0.7 0 0 --steps 450

A foot near 1.0 never lifts; near 0.0 it is held up (a three-legged gait); a walking trot
has every foot between about 0.4 and 0.8.
"""

from __future__ import annotations

import glob

import click
import numpy as np

from mat_sdk import envs
from mat_sdk.evaluation.episodes import CheckpointPolicy


def contact_shares(path: str, command: tuple[float, float, float], steps: int, seed: int):
    """(foot names, each foot's share of `steps` steps in contact) for one checkpoint."""
    loaded = CheckpointPolicy.from_checkpoint(path)
    trained = loaded.training.env  # the user named these files: their env ids are imported
    team = envs.make_team(trained.id, seed=seed, command=list(command), **trained.team_options)
    layout = team.wiring().observation
    (start, stop), feet = layout.source["contacts"], layout.signals["contacts"]
    obs = team.reset(seed=seed)
    warmup = round(1.0 / team.control_timestep)
    touching = np.zeros(stop - start)
    for step in range(warmup + steps):
        action = loaded.act(obs[None])[0]
        obs, _, terminated, truncated = team.advance(action)
        if step >= warmup:
            touching += team.observations.source()[start:stop] > 0
        if terminated or truncated:
            break
    return feet, touching / steps


@click.command()
@click.argument("patterns", nargs=-1, required=True)
@click.option("--command", type=float, nargs=3, default=(0.7, 0.0, 0.0), show_default=True)
@click.option("--steps", default=450, show_default=True, help="steps counted after the first s")
@click.option("--seed", default=10_000, show_default=True)
def main(patterns, command, steps, seed) -> None:
    for path in sorted(p for pattern in patterns for p in glob.glob(pattern)):
        feet, shares = contact_shares(path, command, steps, seed)
        print(
            f"{path}: "
            + " / ".join(f"{foot} {share:.2f}" for foot, share in zip(feet, shares, strict=False))
        )


if __name__ == "__main__":
    main()
