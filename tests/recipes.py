"""The learning recipes the tests rely on: what each learning test trains, the score it
asserts on and its bound (`RECIPES`).

A learning test must hold on every seed and every CPU (float rounding differs between
them), not pass by one lucky trajectory: `python -m benchmarks.seeds` (`benchmarks.seeds`) runs a
recipe on many seeds and prints the per-seed table, so anyone can re-check that the test's
bound holds with margin.
"""

from __future__ import annotations

import tempfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mat_sdk.evaluation.episodes import EVALUATION_SEED, random_team_return

# PPO settings under which MAT solves `coordination-3` in a few thousand steps, on every seed
# swept. Once the game is solved the advantages are the critic's noise: the std floor keeps
# that noise small (TrainConfig.advantage_std_floor), and a small entropy bonus (0.003, not
# 0.01) keeps the bonus itself from pushing a solved policy back towards uniform choices.
GAME = {
    "num_envs": 32,
    "rollout_length": 8,
    "lr": 5e-4,
    "ppo_epochs": 4,
    "num_minibatches": 2,
    "clip": 0.2,
    "entropy_coef": 0.003,
    "advantage_std_floor": 0.05,
}
GAME_STEPS = 16_000


def train_returns(env_id: str, algo: str, steps: int, **options) -> list[float]:
    """The mean return of the episodes finished in each update (nan where none finished)."""
    from mat_sdk.training.trainer import Trainer

    returns: list[float] = []
    with Trainer(env_id, algo, **options) as trainer:
        trainer.learn(
            steps, progress_bar=False, callback=lambda t, m: returns.append(m["return_mean"])
        )
    return returns


def game_return(algo: str = "mat", seed: int = 0, **options) -> float:
    """Mean return of the last 5 updates on `coordination-3` with the GAME recipe."""
    returns = train_returns("coordination-3", algo, GAME_STEPS, seed=seed, **GAME, **options)
    return float(np.mean(returns[-5:]))


def onnx_game_return(seed: int = 0) -> float:
    """The GAME recipe acting through ONNX Runtime in its rollouts: last-5 mean return."""
    return game_return("mat", seed, rollout_backend="onnx")


FINETUNE_CHANGE = {"agent_1": "remove"}  # 3 agents -> 2; agent_2 now follows agent_0 directly
FINETUNE_UPDATES = 10


def pretrain_game(path: str | Path, seed: int = 0) -> Path:
    """A MAT trained on `coordination-3` with the GAME recipe, saved to `path`."""
    from mat_sdk.training.trainer import Trainer

    with Trainer("coordination-3", "mat", seed=seed, **GAME) as trainer:
        trainer.learn(GAME_STEPS, progress_bar=False)
        return trainer.save(path)


def finetune_against_scratch(
    pretrained: str | Path, out_dir: str | Path, seed: int = 0
) -> tuple[list[float], list[float], float]:
    """Fine-tune the pre-trained game policy to a team without agent_1, and train the same
    team from scratch with the same steps: (fine-tuned returns per update, scratch returns per
    update, the fine-tuned policy's final evaluation over 20 episodes)."""
    from mat_sdk.training.finetune import finetune

    steps = FINETUNE_UPDATES * GAME["num_envs"] * GAME["rollout_length"]
    finetuned: list[float] = []
    result = finetune(
        pretrained, faults=FINETUNE_CHANGE, steps=steps, out_dir=out_dir, lr=1e-4, seed=seed,
        eval_episodes=20, progress_bar=False,
        callback=lambda t, m: finetuned.append(m["return_mean"]),
    )  # fmt: skip
    result.trainer.close()
    scratch = train_returns(
        "coordination-3", "mat", steps, seed=seed, faults=FINETUNE_CHANGE, **GAME
    )
    return finetuned, scratch, result.final_mean


def _finetune_run(seed: int) -> tuple[list[float], list[float], float]:
    with tempfile.TemporaryDirectory() as tmp:
        pretrained = pretrain_game(Path(tmp) / "pre.pt", seed)
        return finetune_against_scratch(pretrained, Path(tmp) / "ft", seed)


def finetuned_return(seed: int = 0) -> float:
    """The fine-tuned policy after 10 updates: the lower of its last-5 training return and its
    final evaluation."""
    finetuned, _, final = _finetune_run(seed)
    return min(float(np.mean(finetuned[-5:])), final)


def finetune_gain(seed: int = 0) -> float:
    """Fine-tuned minus from-scratch last-5 mean return, after 10 updates each."""
    finetuned, scratch, _ = _finetune_run(seed)
    return float(np.mean(finetuned[-5:]) - np.mean(scratch[-5:]))


CONTINUOUS_ENV = "cheetah-2x3"
CONTINUOUS_OPTIONS = {"episode_limit": 100}
CONTINUOUS = {
    "num_envs": 16,
    "rollout_length": 50,
    "lr": 1e-3,
    "ppo_epochs": 5,
    "num_minibatches": 4,
    "clip": 0.2,
    "entropy_coef": 0.0,
}
CONTINUOUS_STEPS = 12_800


def continuous_return(seed: int = 0, algo: str = "mat") -> float:
    """A short run on the two-leg cheetah (100-step episodes): mean of the last 4 updates."""
    returns = train_returns(
        CONTINUOUS_ENV, algo, CONTINUOUS_STEPS, seed=seed, env_options=CONTINUOUS_OPTIONS,
        **CONTINUOUS,
    )  # fmt: skip
    return float(np.nanmean(returns[-4:]))


def continuous_bound() -> float:
    """What the continuous run must beat: 3x a random team's return, and at least 2."""
    return max(2.0, 3 * random_team_return(CONTINUOUS_ENV, **CONTINUOUS_OPTIONS))


# Your own envs (docs/CUSTOM_ENVS.md): `examples/my_robots.py` (a custom MJCF arm) and
# `examples/mpe_envs.py` (MPE through PettingZoo), by their module:function ids.
EXAMPLES = Path(__file__).resolve().parents[1] / "examples"
ARM_ENV = "my_robots:arm"
ARM = {**CONTINUOUS, "lr": 3e-3, "ppo_epochs": 10, "num_minibatches": 2}
ARM_STEPS = 12_000
SPREAD = {
    "num_envs": 16,
    "rollout_length": 25,
    "lr": 5e-4,
    "ppo_epochs": 5,
    "num_minibatches": 2,
    "clip": 0.2,
    "entropy_coef": 0.01,
}
SPREAD_STEPS = 32_000
# Continuous simple_spread learns more slowly: three times the steps (a slow test).
SPREAD_CONTINUOUS_STEPS = 96_000
SPREAD_EVALUATIONS = 32
ARM_FRACTION = 0.5  # returns are negative: half a random team's distance cost
# A random team's 32-episode mean varies by ~0.35 between action draws on the same starts
# (discrete -25.0, continuous -23.6 on average): these bounds sit 7 and 3.5 of those above.
SPREAD_FRACTION = 0.9
SPREAD_CONTINUOUS_FRACTION = 0.96


def with_examples() -> None:
    """Make the example env modules importable (they live beside the package, not in it)."""
    import sys

    if str(EXAMPLES) not in sys.path:
        sys.path.insert(0, str(EXAMPLES))


def arm_return(seed: int = 0) -> float:
    """MAT on the custom arm: mean return of the last 3 updates."""
    with_examples()
    return float(np.nanmean(train_returns(ARM_ENV, "mat", ARM_STEPS, seed=seed, **ARM)[-3:]))


def spread_return(
    seed: int = 0,
    env_id: str = "mpe_envs:spread",
    steps: int = SPREAD_STEPS,
    algo: str = "mat",
    out_dir: str | Path | None = None,
) -> float:
    """MAT (or `algo`) on MPE simple_spread through from_pettingzoo: the mean return of 32
    evaluation episodes (deterministic) after training; a start's layout alone swings a
    return by several units, so a few training episodes would not tell."""
    from mat_sdk.training.trainer import Trainer

    with_examples()
    with Trainer(env_id, algo, out_dir=out_dir, seed=seed, **SPREAD) as trainer:
        trainer.learn(steps, progress_bar=False)
        return float(np.mean(trainer.evaluate(SPREAD_EVALUATIONS)))


def beats_random(env_id: str, fraction: float) -> float:
    """A bound for negative-return envs: `fraction` of a random team's (negative) return, on
    the episode starts that `Trainer.evaluate` uses (so start layouts do not count)."""
    with_examples()
    return fraction * random_team_return(env_id, SPREAD_EVALUATIONS, seed=EVALUATION_SEED)


@dataclass(frozen=True)
class Recipe:
    run: Callable[[int], float]
    bound: Callable[[], float]
    above: bool  # the score must be >= bound (True) or <= bound (False)
    claim: str


RECIPES: dict[str, Recipe] = {
    "game-mat": Recipe(
        lambda seed: game_return("mat", seed),
        lambda: 0.9,
        True,
        "MAT solves coordination-3: last-5 return >= 0.9",
    ),
    "game-mat-dec": Recipe(
        lambda seed: game_return("mat-dec", seed),
        lambda: 0.5,
        False,
        "MAT-Dec cannot: last-5 return <= 0.5 (its best is 1/3)",
    ),
    "game-happo": Recipe(
        lambda seed: game_return("happo", seed),
        lambda: 0.25,
        True,
        "HAPPO reaches the decentralised best (1/3): last-5 return >= 0.25",
    ),
    "game-onnx": Recipe(
        onnx_game_return, lambda: 0.9, True, "ONNX Runtime rollouts solve it: last-5 >= 0.9"
    ),
    "finetune": Recipe(
        finetuned_return,
        lambda: 0.95,
        True,
        "fine-tuning to a removed agent: last-5 return and final evaluation >= 0.95",
    ),
    "finetune-gain": Recipe(
        finetune_gain,
        lambda: 0.15,
        True,
        "fine-tuning beats scratch on a removed agent by >= 0.15 (last-5 return)",
    ),
    "continuous": Recipe(
        continuous_return,
        continuous_bound,
        True,
        "a short cheetah-2x3 run beats max(2, 3x a random team)",
    ),
    "continuous-happo": Recipe(
        lambda seed: continuous_return(seed, "happo"),
        continuous_bound,
        True,
        "HAPPO's short cheetah-2x3 run beats it too",
    ),
    "arm": Recipe(
        arm_return,
        lambda: beats_random(ARM_ENV, ARM_FRACTION),
        True,
        f"MAT on the custom MJCF arm: last-3 return >= {ARM_FRACTION} x a random team's",
    ),
    "spread": Recipe(
        spread_return,
        lambda: beats_random("mpe_envs:spread", SPREAD_FRACTION),
        True,
        f"MAT on MPE simple_spread (discrete), {SPREAD_STEPS} steps: evaluation >= "
        f"{SPREAD_FRACTION} x a random team's",
    ),
    "spread-continuous": Recipe(
        lambda seed: spread_return(seed, "mpe_envs:spread_continuous", SPREAD_CONTINUOUS_STEPS),
        lambda: beats_random("mpe_envs:spread_continuous", SPREAD_CONTINUOUS_FRACTION),
        True,
        f"continuous actions, {SPREAD_CONTINUOUS_STEPS} steps: evaluation >= "
        f"{SPREAD_CONTINUOUS_FRACTION} x a random team's",
    ),
}
