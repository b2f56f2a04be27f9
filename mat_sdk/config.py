"""`TrainConfig`: every training option, with its default and its check.

A run starts from a named recipe (`RECIPES`, `TrainConfig.for_algo`): "fast", the default, or
"paper", the MAT paper's MA-MuJoCo recipe (docs/ALGORITHM.md has both and why). The dataclass
defaults are the paper's MAT recipe. A bad value is refused when the config is made, before
any env worker starts, with an error that names the field.
"""

from __future__ import annotations

import math
import numbers
import re
from dataclasses import dataclass, field, fields
from typing import TYPE_CHECKING, Any

from mat_sdk.algorithms import algorithm

if TYPE_CHECKING:  # torch and the model load only when used: the CLI reads defaults here
    from mat_sdk.model import ModelConfig

ROLLOUT_BACKENDS = ("torch", "onnx")

# The named recipes a run starts from; each algorithm's changes to the dataclass defaults
# (the paper's MAT recipe) are its own (`Algorithm.recipes`). "paper": the MAT paper's
# MA-MuJoCo settings, 10 epochs x 40 minibatches = 400 small Adam steps per 4,000 env steps
# (MAPPO, HAPPO: their papers' own), tuned for GPU throughput. "fast": the same data per update
# in few large minibatches with a larger step: on a CPU the update is bound by the number of
# optimizer steps, not by their size (docs/ALGORITHM.md has the search and its measurements);
# measured for MAT only, the others keep their paper's settings under it.
RECIPES = ("paper", "fast")
DEFAULT_RECIPE = "fast"


# What each numeric option must be: (fields, test, the rule as the error states it).
# `None` passes (critic_lr's default: the actor's rate).
_RULES = (
    (
        ("num_envs", "rollout_length", "lr", "critic_lr", "adam_eps", "ppo_epochs",
         "num_minibatches", "clip", "huber_delta", "max_grad_norm", "n_embd", "n_head",
         "n_block", "checkpoint_every"),
        lambda x: x > 0,
        "> 0",
    ),
    (
        ("workers", "update_workers", "entropy_coef", "value_coef", "torch_threads",
         "advantage_std_floor"),
        lambda x: x >= 0,
        ">= 0",
    ),
    (("gamma", "gae_lambda"), lambda x: 0 <= x <= 1, "in [0, 1]"),
    # env copy i is seeded seed + i, and MuJoCo tasks' numpy streams take seeds below 2**32
    (("seed",), lambda x: 0 <= x < 2**31, "in 0..2**31 - 1"),
    (("attention_window",), lambda x: x >= 2, ">= 2 or null"),
)  # fmt: skip


@dataclass
class TrainConfig:
    env: str = "cheetah-6x1"
    # Further env ids of one family (other agent counts, one observation size): updates
    # alternate between `env` and these, so one policy learns every count.
    more_envs: list[str] = field(default_factory=list)
    algo: str = "mat"
    # The named starting point of the hyperparameters below (`RECIPES`); provenance, and what
    # `for_algo` applies. Runs from before recipes existed were the paper's.
    recipe: str = "paper"
    faults: dict[str, str] = field(default_factory=dict)
    env_options: dict[str, Any] = field(default_factory=dict)  # e.g. {"agent_id": False}
    seed: int = 0
    num_envs: int = 40
    workers: int = 0
    # Processes that each compute the gradient of a share of every minibatch (CPU), using
    # cores a rollout leaves idle (BENCHMARKS.md has the speed-ups). 0: this process alone.
    update_workers: int = 0
    rollout_length: int = 100
    lr: float = 5e-5
    critic_lr: float | None = None  # MAPPO's critic; None: same as lr
    adam_eps: float = 1e-5
    ppo_epochs: int = 10
    num_minibatches: int = 40
    clip: float = 0.05
    entropy_coef: float = 0.001
    value_coef: float = 1.0
    huber_delta: float = 10.0
    max_grad_norm: float = 0.5
    gamma: float = 0.99
    gae_lambda: float = 0.95
    # Advantages are scaled by their batch std, floored at this (reward units). When nearly
    # every sample earns the same return, that std is only the critic's error, and dividing by
    # it turns the error into full-size policy steps that drift a solved policy away (the
    # coordination game). 0: the official 1e-5 epsilon only.
    advantage_std_floor: float = 0.0
    n_embd: int = 64
    n_head: int = 1
    n_block: int = 1
    # MAT: attend only to agents fewer than this many places away (None: all; the paper's).
    # Linear cost in the agent count instead of quadratic (docs/ALGORITHM.md).
    attention_window: int | None = None
    shuffle_agents: bool = False  # the paper shuffles the order; the official code does not
    normalize_obs: bool = True
    checkpoint_every: int = 10  # updates
    device: str = "cpu"
    compile: bool = False  # torch.compile the loss: faster updates after a slow compile
    # "onnx": act in rollouts through ONNX Runtime (mat_sdk.onnx_actor), else torch.
    rollout_backend: str = "torch"
    # Small MAT ops are dispatch-bound, so one thread beats several (BENCHMARKS.md) and
    # leaves the other cores to env and update workers. 0: torch's default.
    torch_threads: int = 1
    # CPU: treat subnormal floats (< 1.2e-38) as zero. Training makes some, and x86 computes
    # with them far slower (BENCHMARKS.md). Process-wide.
    flush_denormal: bool = True
    # Fine-tuning provenance (Trainer.from_pretrained): the checkpoint the weights came from.
    init_from: str | None = None
    # Ray: "local" or a cluster address. Rollouts then run on `workers` Ray actors, each
    # stepping its share of the num_envs copies; the learner (this process) updates.
    ray: str | None = None

    def __post_init__(self):
        """Refuse a bad value here, before any env worker starts, naming the field."""
        integer = {f.name for f in fields(self) if f.type in ("int", "int | None")}
        for names, ok, rule in _RULES:
            for name in names:
                value = getattr(self, name)
                if value is None:
                    continue
                kind = numbers.Integral if name in integer else numbers.Real
                number = isinstance(value, kind) and not isinstance(value, bool)
                if not (number and math.isfinite(value) and ok(value)):
                    what = "an integer" if name in integer else "a number"
                    raise ValueError(f"{name} must be {what} {rule}, got {value!r}")
                # numpy scalars become Python numbers: checkpoints load with weights_only
                setattr(self, name, int(value) if name in integer else float(value))
        for f in fields(self):
            value, optional = getattr(self, f.name), f.type.endswith("| None")
            if value is None and optional:
                continue
            if f.type == "bool" and not isinstance(value, bool):
                raise ValueError(f"{f.name} must be true or false, got {value!r}")
            if f.type.startswith("dict") and not (
                isinstance(value, dict) and all(isinstance(k, str) for k in value)
            ):
                raise ValueError(
                    f"{f.name} must be a mapping with string keys such as {{...}}, got {value!r}"
                )
            if f.type.startswith("str") and not isinstance(value, str):
                raise ValueError(f"{f.name} must be a string, got {value!r}")
            if f.type.startswith("list") and not (
                isinstance(value, list) and all(isinstance(v, str) for v in value)
            ):
                raise ValueError(f"{f.name} must be a list of strings, got {value!r}")
        if "seed" in self.env_options:
            raise ValueError(
                "env_options cannot set seed: env copy i is seeded with the run's seed + i"
            )
        if not all(isinstance(mode, str) for mode in self.faults.values()):
            raise ValueError(
                f"faults must map names to 'zero', 'remove' or 'weak:S', got {self.faults!r}"
            )
        if algorithm(self.algo).sequential_update and (self.update_workers or self.compile):
            raise ValueError(
                f"{self.algo.upper()} updates its agents one after another in this process: "
                "update_workers and compile do not apply to it; leave them at 0 and false"
            )
        if self.recipe not in RECIPES:
            raise ValueError(f"recipe must be one of {', '.join(RECIPES)}, got {self.recipe!r}")
        if self.rollout_backend not in ROLLOUT_BACKENDS:
            raise ValueError(
                f"rollout_backend must be one of {', '.join(ROLLOUT_BACKENDS)}, "
                f"got {self.rollout_backend!r}"
            )
        if not re.fullmatch(r"cpu|auto|cuda(:\d+)?", self.device):
            raise ValueError(f"device must be cpu, cuda, cuda:N or auto, got {self.device!r}")

    def configure_torch(self) -> None:
        """Apply the process-wide torch settings, in the trainer and in its update workers."""
        import torch

        if self.torch_threads:
            torch.set_num_threads(self.torch_threads)
        torch.set_flush_denormal(self.flush_denormal)  # both ways: a process may train twice

    def resolve_device(self):
        """The torch device to train on ("auto": CUDA where torch sees it, else the CPU), or
        ValueError for one this machine or these options cannot use."""
        import torch

        if self.device == "auto":
            device = torch.device("cuda" if torch.cuda.is_available() else "cpu")
        else:
            device = torch.device(self.device)
        if device.type == "cuda" and not torch.cuda.is_available():
            raise ValueError(
                "device 'cuda' requested but torch sees no CUDA device; use --device cpu"
            )
        if self.update_workers and device.type != "cpu":
            raise ValueError(
                "update_workers splits CPU updates over processes; on a GPU use update_workers=0"
            )
        return device

    def check_batching(self) -> None:
        """Refuse minibatches that cannot be formed, or split over the update workers."""
        per_update = self.num_envs * self.rollout_length
        if self.num_minibatches > per_update:
            raise ValueError(
                f"num_minibatches {self.num_minibatches} > env-steps per update {per_update} "
                "(num_envs x rollout_length)"
            )
        if per_update // self.num_minibatches < self.update_workers + 1:
            raise ValueError(
                f"update_workers {self.update_workers}: a minibatch of "
                f"{per_update // self.num_minibatches} env-steps cannot be split "
                f"{self.update_workers + 1} ways; use fewer update workers or minibatches"
            )

    @property
    def env_ids(self) -> list[str]:
        """Every env id trained on: `env`, then `more_envs`."""
        return [self.env, *self.more_envs]

    def make_envs(
        self, num_envs: int | None = None, workers: int | None = None, env_id: str | None = None
    ):
        """The vectorised envs this config trains on (default: `num_envs` copies of `env`
        stepped by `workers` processes), copy i seeded `seed + i`."""
        from mat_sdk import envs

        return envs.make_vec(
            env_id or self.env,
            self.num_envs if num_envs is None else num_envs,
            workers=self.workers if workers is None else workers,
            seed=self.seed,
            faults=self.faults,
            **self.env_options,
        )

    def model_config(self, env) -> ModelConfig:
        """The model this config trains on `env` (its observation, action and team sizes)."""
        from mat_sdk.model import ModelConfig

        return ModelConfig(
            obs_dim=env.obs_dim,
            action_size=env.action_size,
            n_agents=env.n_agents,
            algo=self.algo,
            action_type=env.action_type,
            n_embd=self.n_embd,
            n_head=self.n_head,
            n_block=self.n_block,
            attention_window=self.attention_window,
        )

    @classmethod
    def for_algo(cls, algo: str, recipe: str = DEFAULT_RECIPE, **overrides: Any) -> TrainConfig:
        """The recipe's hyperparameters for `algo`, then the caller's overrides."""
        unknown = set(overrides) - {f.name for f in fields(cls)}
        if unknown:
            raise ValueError(f"unknown training option(s) {sorted(unknown)}")
        # an unknown recipe gets no settings here and is refused by the config's own check
        recipes = algorithm(algo).recipes
        settings = recipes.get(recipe, recipes.get("paper", {}))
        return cls(**{"algo": algo, "recipe": recipe, **settings, **overrides})
