"""Success rates of bimanual reaching policies (examples/bimanual.py): each arm's hand within
2 cm of its target when the episode ends, on the nominal arms and on randomized ones.

    PYTHONPATH=examples python -m benchmarks.bimanual_success \\
        --group plain='runs/bimanual/seed_*/checkpoint.pt' \\
        --group randomized='runs/bimanual-rand/seed_*/checkpoint.pt' --episodes 50
"""

from __future__ import annotations

import glob

import click
import numpy as np

from mat_sdk import envs
from mat_sdk.evaluation.episodes import CheckpointPolicy, one_torch_thread
from tests.recipes import with_examples

with_examples()
import bimanual  # noqa: E402  (examples/, put on the path just above)


def final_distances(path: str, episodes: int, randomize: bool, seed: int = 10_000) -> np.ndarray:
    """[episodes, 2]: each hand's distance to its target at the end of an episode (m)."""
    loaded = CheckpointPolicy.from_checkpoint(path)
    with (
        one_torch_thread(),
        envs.make_vec("bimanual:reach", episodes, seed=seed, randomize=randomize) as vec,
    ):
        wiring = envs.make_team("bimanual:reach").wiring()
        features = {f.name: f for f in wiring.observation.features}
        columns = {name: features[f"sensor.{name}"] for name in bimanual.SENSORS}
        obs = vec.reset(seed=seed)
        distances = np.full((episodes, 2), np.nan)
        while np.isnan(distances).any():
            obs, _, _, _, info = vec.step(loaded.act(obs))
            first = info["done"] & np.isnan(distances[:, 0])
            final = info["final_obs"][first, 0]  # every agent observes both reaches
            for k, arm in enumerate(bimanual.ARMS):
                hand, target = (columns[f"{arm}_{part}"] for part in ("hand", "target"))
                gap = final[:, target.start : target.stop] - final[:, hand.start : hand.stop]
                distances[first, k] = np.linalg.norm(gap, axis=1)
    return distances


@click.command()
@click.option("--group", "groups", multiple=True, required=True, metavar="LABEL=GLOB")
@click.option("--episodes", default=50, show_default=True)
def main(groups, episodes: int) -> None:
    print(f"{episodes} episodes per policy and env; success: a hand ends within "
          f"{bimanual.SUCCESS * 100:g} cm of its target (both arms counted).\n")  # fmt: skip
    print("| trained | seed | nominal arms: success | final distance (cm) | randomized arms: "
          "success | final distance (cm) |\n|---|---|---|---|---|---|")  # fmt: skip
    for group in groups:
        label, _, pattern = group.partition("=")
        paths = sorted(glob.glob(pattern))
        if not paths:
            raise click.BadParameter(f"{pattern!r} matches no checkpoint", param_hint="--group")
        for path in paths:
            cells = []
            for randomize in (False, True):
                distances = final_distances(path, episodes, randomize)
                success = float(np.mean(distances < bimanual.SUCCESS))
                cells += [f"{success:.0%}", f"{np.median(distances) * 100:.1f} (median)"]
            print(f"| {label} | {path} | " + " | ".join(cells) + " |")


if __name__ == "__main__":
    main()
