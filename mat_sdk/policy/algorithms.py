"""The training algorithms by name, and the one place that tells them apart.

    algorithm("happo").sequential_update   # True: its agents update one after another

Callers ask an algorithm's properties (how it acts, what its critic reads, how it updates,
which recipe settings it starts from), never its policy's class or its name: adding an
algorithm is one entry here and its policy class in `mat_sdk.policy.model`. The names are the
runtime's (`mat_runtime.manifest.ALGOS`), the list a bundle's manifest is checked against.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

from mat_runtime.manifest import ALGOS, FIXED_TEAM


@dataclass(frozen=True)
class Algorithm:
    name: str
    # agents act one after another, each seeing the actions before it (MAT's decoder); the
    # bundle exports an encoder and a decoder step. Otherwise every agent acts at once.
    autoregressive: bool = False
    # the critic reads every agent's observation at once (MAPPO's and HAPPO's MLP), so the
    # policy is tied to the agent count it was trained on
    centralised_critic: bool = False
    actor_per_agent: bool = False  # separate actor weights per agent (HAPPO)
    # agents update one after another, each on the others' new policy (`mat_sdk.training.happo`):
    # no update workers, torch.compile or tuning of them
    sequential_update: bool = False
    # each named recipe's changes to the training defaults (`mat_sdk.policy.config.RECIPES`); an
    # algorithm without settings of a recipe's own trains with its "paper" ones
    recipes: Mapping[str, Mapping[str, Any]] = field(default_factory=dict)

    @property
    def bundle_kind(self) -> str:
        """How the exported bundle acts (its manifest's `kind`)."""
        return "autoregressive" if self.autoregressive else "decentralised"


# The MAT paper's MA-MuJoCo update over the defaults' "fast" one (`mat_sdk.policy.config.RECIPES`)
PAPER_MAT = {"lr": 5e-5, "ppo_epochs": 10, "num_minibatches": 40, "clip": 0.05}

ALGORITHMS: dict[str, Algorithm] = {
    a.name: a
    for a in (
        Algorithm(
            "mat",
            autoregressive=True,
            recipes={"fast": {}, "paper": PAPER_MAT},  # the defaults are its "fast" recipe
        ),
        Algorithm("mat-dec", recipes={"paper": PAPER_MAT}),
        Algorithm(
            "mappo",
            centralised_critic=True,
            recipes={
                "paper": {**PAPER_MAT, "lr": 5e-6, "critic_lr": 5e-3, "ppo_epochs": 5, "clip": 0.2}
            },
        ),
        Algorithm(
            "happo",
            centralised_critic=True,
            actor_per_agent=True,
            sequential_update=True,
            # HARL's tuned MA-MuJoCo HAPPO (e.g. Walker2d 2x3): 5 epochs x 2 minibatches, lr
            # 1e-3 for actors and critic, clip 0.05, no entropy bonus, gradient norm 10
            recipes={
                "paper": {
                    "lr": 1e-3,
                    "critic_lr": 1e-3,
                    "ppo_epochs": 5,
                    "num_minibatches": 2,
                    "clip": 0.05,
                    "entropy_coef": 0.0,
                    "max_grad_norm": 10.0,
                }
            },
        ),
    )
}


def algorithm(name: str) -> Algorithm:
    """The algorithm called `name`, or ValueError listing the valid names."""
    if name not in ALGORITHMS:
        raise ValueError(f"unknown algo {name!r}; valid: {', '.join(ALGORITHMS)}")
    return ALGORITHMS[name]


def _check_against_runtime() -> None:
    """The runtime checks bundles against its own list of names and fixed-team algorithms;
    this registry must describe the same ones."""
    fixed = tuple(a.name for a in ALGORITHMS.values() if a.centralised_critic)
    if tuple(ALGORITHMS) != ALGOS or fixed != FIXED_TEAM:
        raise ImportError(
            f"mat_sdk.policy.algorithms {tuple(ALGORITHMS)} (fixed team {fixed}) disagrees with "
            f"mat_runtime.manifest {ALGOS} (fixed team {FIXED_TEAM})"
        )


_check_against_runtime()
