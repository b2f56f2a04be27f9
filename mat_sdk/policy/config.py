"""A training run's configuration: small frozen parts, each with one default and its checks.

    config = TrainConfig.for_algo("mat", env="go2:walk", lr=1e-3, seed=2)   # flat options
    config.ppo.lr, config.run.seed, config.env.faults                       # typed parts

- `EnvConfig`: what is trained on (the env ids, their options, the robot's faults);
- `PPOConfig`: the update (batch shape, rates, epochs, clip, coefficients);
- `NetworkConfig`: the policy network's size;
- `RunConfig`: how the run is computed (seed, workers, device, checkpoints), which a resume
  may change in part;
- `TrainConfig`: those four, the algorithm and the recipe they started from.

Users, the CLI (`--set lr=3e-4`) and task recipes give options by their flat names (`lr`,
`num_envs`, `faults`; `OPTIONS`); `TrainConfig.for_algo` routes each to its part. A run
starts from a named recipe (`RECIPES`): "fast", the default, or "paper", the MAT paper's
MA-MuJoCo recipe (each algorithm's settings: `mat_sdk.policy.algorithms`; docs/ALGORITHM.md has both
and why). A bad value is refused where its part is made, before any env worker starts, with
an error that names the option. Checkpoints store `to_dict()`, the parts by name; files
written before the parts existed (one flat mapping) load the same (`from_dict`).
"""

from __future__ import annotations

import math
import numbers
import re
from collections.abc import Mapping
from dataclasses import dataclass, field, fields, replace
from typing import TYPE_CHECKING, Any

from mat_sdk.envs.core.faults import Fault, as_mapping, faults_of
from mat_sdk.policy.algorithms import algorithm

if TYPE_CHECKING:  # torch and the model load only when used: the CLI reads defaults here
    from mat_sdk.policy.model import ModelConfig

ROLLOUT_BACKENDS = ("torch", "onnx")

# The named recipes a run starts from; each algorithm's changes to the defaults below are its
# own (`Algorithm.recipes`). "fast" (the defaults, for MAT): few large minibatches with a large
# step, as HARL's tuned MA-MuJoCo recipes do: on a CPU the update is bound by the number of
# optimizer steps, not by their size (docs/ALGORITHM.md has the search and its measurements).
# "paper": the MAT paper's MA-MuJoCo settings, 10 epochs x 40 minibatches = 400 small Adam
# steps per 4,000 env steps (MAPPO, HAPPO: their own papers'), tuned for GPU throughput.
RECIPES = ("paper", "fast")
DEFAULT_RECIPE = "fast"


def _check_numbers(part: Any, rules: tuple) -> None:
    """Refuse a number outside its rule, naming the option; numpy scalars become Python
    numbers (checkpoints load with weights_only). `rules`: (names, test, the rule in words);
    None passes (an option whose default is "not set")."""
    integer = {f.name for f in fields(part) if f.type in ("int", "int | None")}
    for names, ok, rule in rules:
        for name in names:
            value = getattr(part, name)
            if value is None:
                continue
            kind = numbers.Integral if name in integer else numbers.Real
            number = isinstance(value, kind) and not isinstance(value, bool)
            if not (number and math.isfinite(value) and ok(value)):
                what = "an integer" if name in integer else "a number"
                raise ValueError(f"{name} must be {what} {rule}, got {value!r}")
            object.__setattr__(part, name, int(value) if name in integer else float(value))


def _check_flags(part: Any, *names: str) -> None:
    for name in names:
        if not isinstance(getattr(part, name), bool):
            raise ValueError(f"{name} must be true or false, got {getattr(part, name)!r}")


def _check_text(part: Any, *names: str) -> None:
    for name in names:
        value = getattr(part, name)
        if value is not None and not isinstance(value, str):
            raise ValueError(f"{name} must be a string, got {value!r}")


def _positive(*names: str) -> tuple:
    return (names, lambda x: x > 0, "> 0")


@dataclass(frozen=True)
class EnvConfig:
    """What is trained on."""

    id: str = "cheetah-6x1"
    # Further env ids of one family (other agent counts, one observation size): updates
    # alternate between `id` and these, so one policy learns every count.
    more: tuple[str, ...] = ()
    options: Mapping[str, Any] = field(default_factory=dict)  # e.g. {"agent_id": False}
    faults: tuple[Fault, ...] = ()  # a sequence of `Fault`s, or their mapping form
    # Training episodes end (truncated: the return past them bootstrapped) after this many
    # control steps: where the env's episodes are long, more of them start per env step, and
    # a policy learns getting going from as many starts as it needs. Only the training envs
    # take it; evaluations, the reward check and exports keep the env's own episode_limit.
    # None: the env's.
    train_episode_limit: int | None = None

    def __post_init__(self):
        _check_text(self, "id")
        _check_numbers(self, (_positive("train_episode_limit"),))
        more = self.more
        if isinstance(more, str) or not all(isinstance(v, str) for v in more):
            raise ValueError(f"more_envs must be a list of strings, got {more!r}")
        object.__setattr__(self, "more", tuple(more))
        options = self.options
        if not (isinstance(options, Mapping) and all(isinstance(k, str) for k in options)):
            raise ValueError(
                f"env_options must be a mapping with string keys such as {{...}}, got {options!r}"
            )
        if "seed" in options:
            raise ValueError(
                "env_options cannot set seed: env copy i is seeded with the run's seed + i"
            )
        object.__setattr__(self, "options", dict(options))
        object.__setattr__(self, "faults", faults_of(self.faults))

    @property
    def ids(self) -> list[str]:
        """Every env id trained on: `id`, then `more`."""
        return [self.id, *self.more]

    @property
    def team_options(self) -> dict[str, Any]:
        """What `envs.make_team` takes to build this env: its options and faults."""
        return {**self.options, "faults": self.faults}

    def make_vec(self, num_envs: int, workers: int, seed: int, env_id: str | None = None):
        """`num_envs` copies of `env_id` (default: `id`) stepped by `workers` processes,
        copy i seeded `seed + i`: the training envs (`train_episode_limit` applies)."""
        from mat_sdk import envs

        options = self.team_options
        if self.train_episode_limit is not None:
            options["episode_limit"] = self.train_episode_limit
        return envs.make_vec(env_id or self.id, num_envs, workers=workers, seed=seed, **options)


@dataclass(frozen=True)
class PPOConfig:
    """The update: MAT's "fast" recipe by default (`RECIPES`)."""

    num_envs: int = 40
    rollout_length: int = 100
    lr: float = 3e-4
    critic_lr: float | None = None  # MAPPO's and HAPPO's critic; None: same as lr
    adam_eps: float = 1e-5
    ppo_epochs: int = 5
    num_minibatches: int = 4
    clip: float = 0.1
    entropy_coef: float = 0.001
    value_coef: float = 1.0
    huber_delta: float = 10.0
    max_grad_norm: float = 0.5
    # A learning rate adapted to keep each minibatch's KL from the rollout's policy near
    # this (rsl_rl's schedule, `mat_sdk.training.adaptive_lr`); `lr` is where it starts.
    # None: a constant `lr`.
    desired_kl: float | None = None
    gamma: float = 0.99
    gae_lambda: float = 0.95
    # Advantages are scaled by their batch std, floored at this (reward units). When nearly
    # every sample earns the same return, that std is only the critic's error, and dividing by
    # it turns the error into full-size policy steps that drift a solved policy away (the
    # coordination game). 0: the official 1e-5 epsilon only.
    advantage_std_floor: float = 0.0
    shuffle_agents: bool = False  # the paper shuffles the order; the official code does not
    normalize_obs: bool = True

    def __post_init__(self):
        positive = ("num_envs", "rollout_length", "lr", "critic_lr", "adam_eps", "ppo_epochs",
                    "num_minibatches", "clip", "huber_delta", "max_grad_norm",
                    "desired_kl")  # fmt: skip
        _check_numbers(self, (
            _positive(*positive),
            (("entropy_coef", "value_coef", "advantage_std_floor"), lambda x: x >= 0, ">= 0"),
            (("gamma", "gae_lambda"), lambda x: 0 <= x <= 1, "in [0, 1]"),
        ))  # fmt: skip
        _check_flags(self, "shuffle_agents", "normalize_obs")
        per_update = self.num_envs * self.rollout_length
        if self.num_minibatches > per_update:
            raise ValueError(
                f"num_minibatches {self.num_minibatches} > env-steps per update {per_update} "
                "(num_envs x rollout_length)"
            )

    @property
    def steps_per_update(self) -> int:
        return self.num_envs * self.rollout_length


@dataclass(frozen=True)
class NetworkConfig:
    """The policy network's size (the paper's MA-MuJoCo model by default)."""

    n_embd: int = 64
    n_head: int = 1
    n_block: int = 1
    # MAT: attend only to agents fewer than this many places away (None: all; the paper's).
    # Linear cost in the agent count instead of quadratic (docs/ALGORITHM.md).
    attention_window: int | None = None

    def __post_init__(self):
        _check_numbers(self, (
            _positive("n_embd", "n_head", "n_block"),
            (("attention_window",), lambda x: x >= 2, ">= 2 or null"),
        ))  # fmt: skip


@dataclass(frozen=True)
class RunConfig:
    """How the run is computed: the same training on other hardware (a resume may change
    `RESUMABLE`)."""

    seed: int = 0
    workers: int = 0  # env worker processes (0: the envs step in this process)
    # Processes that each compute the gradient of a share of every minibatch (CPU), using
    # cores a rollout leaves idle (BENCHMARKS.md has the speed-ups). 0: this process alone.
    update_workers: int = 0
    device: str = "cpu"
    compile: bool = False  # torch.compile the loss: faster updates after a slow compile
    # "onnx": act in rollouts through ONNX Runtime (mat_sdk.training.onnx_actor), else torch.
    rollout_backend: str = "torch"
    # Small MAT ops are dispatch-bound, so one thread beats several (BENCHMARKS.md) and
    # leaves the other cores to env and update workers. 0: torch's default.
    torch_threads: int = 1
    # CPU: treat subnormal floats (< 1.2e-38) as zero. Training makes some, and x86 computes
    # with them far slower (BENCHMARKS.md). Process-wide.
    flush_denormal: bool = True
    checkpoint_every: int = 10  # updates
    # Ray: "local" or a cluster address. Rollouts then run on `workers` Ray actors, each
    # stepping its share of the num_envs copies; the learner (this process) updates.
    ray: str | None = None

    RESUMABLE = ("device", "workers", "update_workers", "checkpoint_every")

    def __post_init__(self):
        _check_numbers(self, (
            _positive("checkpoint_every"),
            (("workers", "update_workers", "torch_threads"), lambda x: x >= 0, ">= 0"),
            # env copy i is seeded seed + i, and MuJoCo tasks' numpy streams take seeds < 2**32
            (("seed",), lambda x: 0 <= x < 2**31, "in 0..2**31 - 1"),
        ))  # fmt: skip
        _check_flags(self, "compile", "flush_denormal")
        _check_text(self, "device", "rollout_backend", "ray")
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


PARTS = {"env": EnvConfig, "ppo": PPOConfig, "network": NetworkConfig, "run": RunConfig}
# An option's flat name -> (its part, its field there): the names users, the CLI and task
# recipes give. The env's fields keep the names they have always had as options.
_RENAMED = {"env": "id", "more_envs": "more", "env_options": "options", "faults": "faults",
            "train_episode_limit": "train_episode_limit"}  # fmt: skip
OPTIONS: dict[str, tuple[str, str]] = {
    **{flat: ("env", name) for flat, name in _RENAMED.items()},
    **{f.name: (part, f.name) for part in ("ppo", "network", "run") for f in fields(PARTS[part])},
    **{name: ("", name) for name in ("algo", "recipe", "init_from")},
}
RESUMABLE = RunConfig.RESUMABLE  # what a resume may change: how the run is computed


@dataclass(frozen=True)
class TrainConfig:
    """Every setting of a training run, in its parts (the module docstring)."""

    env: EnvConfig = field(default_factory=EnvConfig)
    algo: str = "mat"
    # The named starting point of the settings (`RECIPES`); provenance, and what `for_algo`
    # applies. Runs from before recipes existed were the paper's.
    recipe: str = DEFAULT_RECIPE
    ppo: PPOConfig = field(default_factory=PPOConfig)
    network: NetworkConfig = field(default_factory=NetworkConfig)
    run: RunConfig = field(default_factory=RunConfig)
    # Fine-tuning provenance (Trainer.from_pretrained): the checkpoint the weights came from.
    init_from: str | None = None

    def __post_init__(self):
        _check_text(self, "algo", "recipe", "init_from")
        method = algorithm(self.algo)  # a known name, or ValueError listing them
        if self.recipe not in RECIPES:
            raise ValueError(f"recipe must be one of {', '.join(RECIPES)}, got {self.recipe!r}")
        for name, kind in PARTS.items():
            if not isinstance(getattr(self, name), kind):
                raise ValueError(f"{name} must be a {kind.__name__}, got {getattr(self, name)!r}")
        run = self.run
        if method.sequential_update and (run.update_workers or run.compile):
            raise ValueError(
                f"{self.algo.upper()} updates its agents one after another in this process: "
                "update_workers and compile do not apply to it; leave them at 0 and false"
            )
        if method.sequential_update and self.ppo.desired_kl is not None:
            raise ValueError(
                f"desired_kl: {self.algo.upper()}'s agents step one after another with a "
                "constant lr; leave desired_kl unset"
            )
        rows = self.ppo.steps_per_update // self.ppo.num_minibatches
        if rows < run.update_workers + 1:
            raise ValueError(
                f"update_workers {run.update_workers}: a minibatch of {rows} env-steps cannot "
                f"be split {run.update_workers + 1} ways; use fewer update workers or minibatches"
            )

    # ---------------------------------------------------------------- flat options
    @classmethod
    def for_algo(
        cls, algo: str = "mat", recipe: str = DEFAULT_RECIPE, **options: Any
    ) -> TrainConfig:
        """The recipe's settings for `algo`, then `options` by their flat names (`OPTIONS`)."""
        unknown = set(options) - set(OPTIONS)
        if unknown:
            raise ValueError(f"unknown training option(s) {sorted(unknown)}")
        # an algorithm without settings of the recipe's own keeps its paper's; an unknown
        # recipe is refused by the config's own check
        recipes = algorithm(algo).recipes
        settings = recipes.get(recipe, recipes.get("paper", {}))
        return cls.from_options({"algo": algo, "recipe": recipe, **settings, **options})

    @classmethod
    def for_task(
        cls, env_id: str, algo: str = "mat", **options: Any
    ) -> tuple[TrainConfig, list[str]]:
        """The config a run of `env_id` trains with, as `Trainer` and `mat train` build it:
        the task's own training recipe (`envs.TrainingRecipe`) under `options`, and a
        family's count-independent identity unless `env_options` says otherwise; and those
        decisions, in words."""
        from mat_sdk import envs

        recipe = envs.recipe_of(env_id)
        task = {k: v for k, v in recipe.settings().items() if k not in options} if recipe else {}
        config = cls.for_algo(algo, env=env_id, **task, **options)
        notes = []
        if task:
            settings = ", ".join(f"{k}={v}" for k, v in task.items())
            notes.append(f"{env_id} trains with its task's recipe: {settings}")
        identity = envs.family_identity(env_id, config.env.options)
        if identity != config.env.options:
            config = replace(config, env=replace(config.env, options=identity))
            notes.append(
                f"{env_id} is a family: agents observe position={envs.FAMILY_IDENTITY!r} "
                "(whether an agent is at an end of the chain, docs/TRANSFER.md); "
                'env_options={"position": null} for none'
            )
        return config, notes

    @classmethod
    def from_options(cls, options: Mapping[str, Any]) -> TrainConfig:
        """A config from flat options (`OPTIONS`); the defaults for the rest."""
        unknown = set(options) - set(OPTIONS)
        if unknown:
            raise ValueError(f"unknown training option(s) {sorted(unknown)}")
        parts: dict[str, dict[str, Any]] = {name: {} for name in PARTS}
        top = {}
        for flat, value in options.items():
            part, name = OPTIONS[flat]
            (parts[part] if part else top)[name] = value
        return cls(**top, **{name: PARTS[name](**given) for name, given in parts.items()})

    def options(self) -> dict[str, Any]:
        """Every setting by its flat name (faults as `Fault`s)."""
        return {
            flat: getattr(getattr(self, part), name) if part else getattr(self, name)
            for flat, (part, name) in OPTIONS.items()
        }

    def with_options(self, **options: Any) -> TrainConfig:
        """This config with `options` (flat names) changed."""
        return TrainConfig.from_options({**self.options(), **options})

    # ---------------------------------------------------------------- checkpoints
    def to_dict(self) -> dict[str, Any]:
        """Plain containers, as a checkpoint stores the config: each part by name."""
        env = self.env
        return {
            "env": {"id": env.id, "more": list(env.more), "options": dict(env.options),
                    "faults": as_mapping(env.faults),
                    "train_episode_limit": env.train_episode_limit},
            "algo": self.algo,
            "recipe": self.recipe,
            **{name: _fields(getattr(self, name)) for name in ("ppo", "network", "run")},
            "init_from": self.init_from,
        }  # fmt: skip

    @classmethod
    def from_dict(cls, stored: Mapping[str, Any]) -> TrainConfig:
        """A config as `to_dict` wrote it, or as one flat mapping of options (checkpoints
        written before the parts existed; without a recipe: the paper's, which they all
        were). Fields newer than the file take their defaults; ValueError for anything else
        wrong, naming it."""
        if not isinstance(stored, Mapping):
            raise ValueError(f"must be a mapping, got {type(stored).__name__}")
        if not isinstance(stored.get("env"), Mapping):  # the flat layout
            options = {"recipe": "paper", **stored}
        else:
            options = cls._flattened(stored)
        missing = [name for name in ("env", "algo") if name not in options]
        if missing:  # a file names what it trained on: no default stands in for it
            raise ValueError(f"names no {' and no '.join(missing)}")
        return cls.from_options(options)

    @staticmethod
    def _flattened(stored: Mapping[str, Any]) -> dict[str, Any]:
        """`to_dict`'s layout as flat options; ValueError for a field this SDK does not know."""
        options: dict[str, Any] = {}
        for key, value in stored.items():
            if key in PARTS:
                if not isinstance(value, Mapping):
                    raise ValueError(f"{key} must be a mapping, got {type(value).__name__}")
                names = {n: f for f, (p, n) in OPTIONS.items() if p == key}
                unknown = sorted(set(value) - set(names), key=str)
                if unknown:
                    raise ValueError(f"{key} has fields this SDK does not know ({unknown[:5]})")
                options.update({names[name]: v for name, v in value.items()})
            elif OPTIONS.get(key, ("?",))[0] == "":
                options[key] = value
            else:
                raise ValueError(f"has fields this SDK does not know ({[key]})")
        return options

    # ---------------------------------------------------------------- what it builds
    def model_config(self, env) -> ModelConfig:
        """The model this config trains on `env` (its observation, action and team sizes)."""
        from mat_sdk.policy.model import ModelConfig

        return ModelConfig(
            obs_dim=env.obs_dim,
            action_size=env.action_size,
            n_agents=env.n_agents,
            algo=self.algo,
            action_type=env.action_type,
            **_fields(self.network),
        )

    def training_envs(self, shapes_only: bool = False) -> list:
        """The vectorised envs of every env id trained on (`make_envs`), each checked to fit
        one policy; with `shapes_only`, one copy of the first in this process, for its shapes
        and names (rollouts run elsewhere: Ray). None is left open if one cannot be made."""
        from mat_sdk.policy.model import check_fits

        if shapes_only and self.env.more:
            raise ValueError("training on several env ids is not offered with Ray yet")
        made = [self.make_envs(1, 0)] if shapes_only else []
        try:
            for other in self.env.ids[len(made) :]:
                made.append(self.make_envs(env_id=other))
            first = self.model_config(made[0])  # one policy must fit every env
            for vec in made[1:]:
                check_fits(first, vec, vec.env_id)
        except BaseException:
            for vec in made:
                vec.close()
            raise
        return made

    def make_envs(
        self, num_envs: int | None = None, workers: int | None = None, env_id: str | None = None
    ):
        """The vectorised envs this config trains on (default: `ppo.num_envs` copies of the
        env stepped by `run.workers` processes), copy i seeded `run.seed + i`."""
        return self.env.make_vec(
            self.ppo.num_envs if num_envs is None else num_envs,
            self.run.workers if workers is None else workers,
            self.run.seed,
            env_id,
        )


def _fields(part: Any) -> dict[str, Any]:
    return {f.name: getattr(part, f.name) for f in fields(part)}


__all__ = ["EnvConfig", "NetworkConfig", "PPOConfig", "RunConfig", "TrainConfig"]
