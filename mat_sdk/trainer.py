"""PPO training of MAT (and MAT-Dec / MAPPO) on vectorised multi-agent envs.

    trainer = Trainer("cheetah-6x1", algo="mat", out_dir="runs/cheetah")
    trainer.learn(200_000)
    trainer.save("cheetah.pt")
    trainer = Trainer.load("cheetah.pt")          # resumes exactly where it stopped
    actions = trainer.predict(obs)                # obs [n, obs_dim] or [B, n, obs_dim]

The hyperparameters start from a named recipe (`recipe="fast"`, the default, or "paper", the
MAT paper's MA-MuJoCo recipe; `config.RECIPES`, docs/ALGORITHM.md); options override them.
"""

from __future__ import annotations

import contextlib
import math
import time
from collections.abc import Callable, Iterator
from dataclasses import asdict
from pathlib import Path
from typing import Any

import torch

from mat_sdk import checkpoint, envs, files, happo, ppo
from mat_sdk.checkpoint import CHECKPOINT_NAME
from mat_sdk.config import TrainConfig
from mat_sdk.envs import Env
from mat_sdk.envs.reward_check import check_reward
from mat_sdk.flat_params import flat_adam
from mat_sdk.gradients import MinibatchGradients
from mat_sdk.model import ModelConfig, PolicyNetwork, build_policy, check_fits
from mat_sdk.normalization import RunningMeanStd, ValueNorm
from mat_sdk.rollout import RolloutCollector, Trajectory
from mat_sdk.run_log import ProgressBar, RunLog, update_metrics


class TrainingDiverged(RuntimeError):
    """A loss became NaN or inf; the last good checkpoint is left as it was."""


class Trainer:
    """Stable-Baselines3-style surface: `learn`, `save`, `load`, `predict`."""

    def __init__(
        self,
        env: Env = "cheetah-6x1",
        algo: str = "mat",
        out_dir: str | Path | None = None,
        **options: Any,
    ):
        """`env`: an env id (`mat envs`, or `module:function`), or a spec from
        `envs.from_dm_control` / `from_mjcf` / `from_pettingzoo` (or a function returning
        one). The checkpoint records the id; a spec's id is known only in this process, a
        module-level function's `module:function` id everywhere. A task that declares a
        training recipe (`envs.TrainingRecipe`) trains with it; `options` override it."""
        env_id = envs.id_of(env)
        recipe = envs.recipe_of(env_id)
        task = {k: v for k, v in recipe.settings().items() if k not in options} if recipe else {}
        self.config = TrainConfig.for_algo(algo, env=env_id, **task, **options)
        cfg = self.config
        self.notes: list[str] = []  # decisions taken for the user, in words
        if task:
            settings = ", ".join(f"{k}={v}" for k, v in task.items())
            self.notes.append(f"{cfg.env} trains with its task's recipe: {settings}")
        self.resumed_with: dict[str, Any] = {}  # how-to-run changes of a resume (`load`)
        identity = envs.family_identity(cfg.env, cfg.env_options)
        if identity != cfg.env_options:
            cfg.env_options = identity
            self.notes.append(
                f"{cfg.env} is a family: agents observe position={envs.FAMILY_IDENTITY!r} "
                "(whether an agent is at an end of the chain, docs/TRANSFER.md); "
                'env_options={"position": null} for none'
            )
        self.device = cfg.resolve_device()
        torch.manual_seed(cfg.seed)
        cfg.configure_torch()
        self._remote = None
        if cfg.ray is not None:
            from mat_sdk.ray_rollouts import RayRollouts

            self._remote = RayRollouts(cfg)
        if cfg.more_envs and self._remote is not None:
            raise ValueError("training on several env ids is not offered with Ray yet")
        # with Ray, one local copy: the env's shapes and names
        self.envs = [cfg.make_envs(1, 0)] if self._remote else []
        try:
            for env_id in cfg.env_ids[len(self.envs) :]:
                self.envs.append(cfg.make_envs(env_id=env_id))
            first = cfg.model_config(self.envs[0])  # one policy must fit every env
            for vec in self.envs[1:]:
                check_fits(first, vec, vec.env_id)
        except BaseException:
            for env in self.envs:
                env.close()
            raise
        self.env = self.envs[0]  # the shapes and names: the first env's
        if self.env.reward_terms and not cfg.init_from:  # warn before training, not after
            self.notes += check_reward(cfg.env, cfg.faults, cfg.seed, cfg.env_options)
        self.model_config = cfg.model_config(self.env)
        self.policy: PolicyNetwork = build_policy(self.model_config).to(self.device)
        self.build_optimizer()
        self.gradients = MinibatchGradients(
            self.policy, self.params, cfg, cfg.update_workers, "default" if cfg.compile else None
        )
        self.value_norm = ValueNorm(device=self.device)
        first = RolloutCollector(self.env, self.policy, cfg, self.device)
        self.collectors = [first] + [
            RolloutCollector(env, self.policy, cfg, self.device, share=first)
            for env in self.envs[1:]
        ]
        self.progress = {"steps": 0, "updates": 0}
        self.out_dir = Path(out_dir) if out_dir is not None else None

    def build_optimizer(self) -> None:
        """Adam over the policy's parameters, laid out flat (`FlatParameters`); MAPPO's
        critic gets its own learning rate when `critic_lr` is set."""
        critic = getattr(self.policy, "critic", None) if self.config.critic_lr else None
        actors = list(self.policy.actors) if self.model_config.algorithm.actor_per_agent else None
        self.params, self.optimizer = flat_adam(
            self.policy, self.config.lr, self.config.adam_eps, critic, self.config.critic_lr,
            parts=actors,
        )  # fmt: skip

    # ------------------------------------------------------------------ acting
    @property
    def collector(self) -> RolloutCollector:
        """The collector of the next update: updates take the env ids in turn."""
        return self.collectors[self.progress["updates"] % len(self.collectors)]

    @property
    def obs_norm(self) -> RunningMeanStd:
        return self.collector.obs_norm

    def predict(self, obs, deterministic: bool = True, available=None):
        """Actions for raw observations (`CheckpointPolicy.predict`): an array [n, obs_dim] or
        [B, n, obs_dim] -> an array, or a PettingZoo obs dict -> an action dict. `available`
        [.., n, choices] (discrete) masks the choices an agent may not take."""
        generator = self.collector.generator
        return self._as_loaded().predict(obs, self.env, deterministic, generator, available)

    # ---------------------------------------------------------------- training
    def learn(
        self,
        total_steps: int,
        callback: Callable[[Trainer, dict], bool | None] | None = None,
        progress_bar: bool = True,
    ) -> Trainer:
        """Train until `total_steps` env steps (counted per env, not per agent) in all.

        `callback(trainer, metrics)` runs after each update; returning False stops training.
        Checkpoints go to `out_dir/checkpoint.pt` every `checkpoint_every` updates and at the end.
        `out_dir` is locked meanwhile (`files.RunLock`): another run there is refused.
        """
        cfg = self.config
        cfg.check_batching()  # refused before the first rollout
        with files.RunLock(self.out_dir) if self.out_dir else contextlib.nullcontext():
            return self._learn(total_steps, callback, progress_bar)

    def _learn(self, total_steps: int, callback, progress_bar: bool) -> Trainer:
        cfg = self.config
        per_update = cfg.num_envs * cfg.rollout_length
        self.gradients.start()  # the update workers start up during the first rollout
        log = RunLog(self.out_dir, resume_after=self.progress["updates"]) if self.out_dir else None
        done = self.progress["steps"]
        bar = ProgressBar(self.planned_steps(total_steps), done, progress_bar)
        try:
            while self.progress["steps"] < total_steps:
                start = time.perf_counter()
                trajectory = self.rollout()
                rolled = time.perf_counter()
                losses = self._update(trajectory)
                updated = time.perf_counter()
                losses |= {**trajectory.diagnostics(), **self._action_std()}
                self.progress["steps"] += per_update
                self.progress["updates"] += 1
                metrics = update_metrics(
                    self.progress, trajectory.finished, trajectory.rewards, losses, per_update,
                    rollout_s=rolled - start, update_s=updated - rolled,
                )  # fmt: skip
                if log:
                    log.write(metrics)
                if self.out_dir and self.progress["updates"] % cfg.checkpoint_every == 0:
                    self.save(self.out_dir / CHECKPOINT_NAME)
                bar.show(metrics, per_update)
                if callback is not None and callback(self, metrics) is False:
                    break
            if self.out_dir:
                self.save(self.out_dir / CHECKPOINT_NAME)
        finally:
            bar.close()
            if log:
                log.close()
        return self

    def planned_steps(self, total_steps: int) -> int:
        """The env steps `learn(total_steps)` ends at: training runs whole updates of
        num_envs x rollout_length steps, so it may go past `total_steps`."""
        per_update = self.config.num_envs * self.config.rollout_length
        done = self.progress["steps"]
        return done + max(0, math.ceil((total_steps - done) / per_update)) * per_update

    @torch.no_grad()
    def rollout(self) -> Trajectory:
        """One update's data: `rollout_length` steps on every env (here or on Ray workers),
        with advantages and returns."""
        if self._remote is not None:
            trajectory = self._remote.collect(self)
            self.obs_norm.update(trajectory.raw_obs)
        else:
            trajectory = self.collector.collect(update_norm=True)
        return self.collector.advantages(trajectory, self.value_norm)

    def _update(self, trajectory: Trajectory) -> dict[str, float]:
        cfg = self.config
        rows = trajectory.rows(cfg.advantage_std_floor)
        if self.model_config.algorithm.sequential_update:  # agents in turn (mat_sdk.happo)
            losses, finite = happo.update(
                self.policy, self.params, self.optimizer, self.value_norm, rows, cfg,
                self.collector.shuffle_generator,
            )  # fmt: skip
            self._check_finite(finite)
            return losses
        self.gradients.share(rows)
        # Accumulate on the device and read once per update: no host sync per minibatch.
        sums = dict.fromkeys(
            ("policy_loss", "value_loss", "entropy", "clip_fraction", "grad_norm"), 0.0
        )
        finite = torch.ones((), dtype=torch.bool, device=self.device)
        count = 0
        for idx in self.minibatches(rows["obs"].shape[0]):
            terms, grad_norm = self.optimizer_step(rows, idx)
            finite &= torch.isfinite(terms.total)
            for key, value in (
                ("policy_loss", terms.policy),
                ("value_loss", terms.value),
                ("entropy", terms.entropy),
                ("clip_fraction", terms.clip_fraction),
                ("grad_norm", grad_norm),
            ):
                sums[key] = sums[key] + value.detach()
            count += 1
        self._check_finite(bool(finite))
        return {key: float(value) / count for key, value in sums.items()}

    def _action_std(self) -> dict[str, float]:
        """The policy's mean action std (continuous actions): how much it still explores."""
        std = self.policy.std()
        return {} if std is None else {"action_std": float(std.detach().mean())}

    def _check_finite(self, finite: bool) -> None:
        if not finite:
            raise TrainingDiverged(
                f"non-finite loss at update {self.progress['updates'] + 1}; training stopped, "
                "the last good checkpoint is kept"
            )

    def minibatches(self, size: int) -> Iterator[torch.Tensor]:
        """The row indices of each optimizer step of an update over `size` rows, shuffled
        from the run's own stream (`ppo.minibatches`)."""
        cfg = self.config
        return ppo.minibatches(
            size, cfg.ppo_epochs, cfg.num_minibatches, self.collector.shuffle_generator,
            self.device,
        )  # fmt: skip

    def optimizer_step(self, rows: dict[str, torch.Tensor], idx: torch.Tensor):
        """One PPO step on the minibatch `idx` of the update's `rows` (already
        shared with `self.gradients`); its loss terms and gradient norm before clipping."""
        returns = rows["returns"][idx]
        self.value_norm.update(returns)
        self.params.zero_grad()
        terms = self.gradients.backward(idx, self.value_norm.normalize(returns))
        grad_norm = self.params.clip_grad_norm_(self.config.max_grad_norm)
        self.optimizer.step()
        return terms, grad_norm

    # ------------------------------------------------------------ checkpoints
    def state_payload(self) -> dict[str, Any]:
        """Everything `Trainer.load` needs to continue exactly (`checkpoint.training_payload`)."""
        return checkpoint.training_payload(
            self.config, self.model_config, self.policy,
            self.params.per_parameter_state(self.optimizer.state_dict()), self.progress,
            self.collectors, self.value_norm,
        )  # fmt: skip

    def save(self, path: str | Path) -> Path:
        """Write a checkpoint atomically (temp file + rename)."""
        return checkpoint.save_atomic(self.state_payload(), path)

    @classmethod
    def load(
        cls,
        path: str | Path,
        out_dir: str | Path | None = None,
        trust_env_code: bool = False,
        **overrides: Any,
    ) -> Trainer:
        """Rebuild a trainer from a checkpoint; `learn` then continues exactly where it stopped.

        Overrides may change how to run (device, workers, update_workers,
        checkpoint_every); any other TrainConfig field given must be the checkpoint's own
        (`checkpoint.training_options`). `resumed_with` holds what changed.
        A `module:function` env id the checkpoint records is imported only when the caller
        names that same id (`env=`, `more_envs=`: typed by the user in this process) or with
        `trust_env_code=True` (`envs.check_trusted`): a checkpoint from elsewhere runs no code.
        """
        payload = checkpoint.load(path)
        train, changed = checkpoint.training_options(payload, path, overrides)
        named = [overrides["env"]] if "env" in overrides else []  # equal to the recorded ones
        named += list(overrides.get("more_envs", []))
        recorded = [train["env"], *train.get("more_envs", [])]
        envs.check_trusted(recorded, trust_env_code, str(path), named=named)
        if envs.is_family(train["env"]):  # trained without an identity: keep it so
            train["env_options"] = {"position": None, **train["env_options"]}
        trainer = cls(train.pop("env"), train.pop("algo"), out_dir=out_dir, **train)
        trainer.resumed_with = changed
        try:
            trainer.progress = checkpoint.restore_training(
                payload, path, policy=trainer.policy, params=trainer.params,
                optimizer=trainer.optimizer, collectors=trainer.collectors,
                value_norm=trainer.value_norm, seed=trainer.config.seed,
            )  # fmt: skip
        except BaseException:
            trainer.close()
            raise
        return trainer

    @classmethod
    def from_pretrained(
        cls,
        checkpoint_path: str | Path,
        env: Env | None = None,
        faults: dict[str, str] | None = None,
        reset_optimizer: bool = True,
        lr: float | None = None,
        out_dir: str | Path | None = None,
        trust_env_code: bool = False,
        action_std: float | None = None,
        **options: Any,
    ) -> Trainer:
        """A new run that starts from a trained policy, for a changed robot (few-shot).

        Takes the checkpoint's weights, model size, observation normaliser, value
        normaliser and hyperparameters; `env`, `faults`, `lr` and `options` (any
        TrainConfig field, e.g. num_envs, seed) change what is trained on and how. Step
        counts start from 0. `reset_optimizer=False` keeps the Adam moments too;
        `action_std` sets a continuous policy's action std afresh (`PolicyNetwork.reset_std`).

        The changed robot must give the same observation and action sizes (a removed agent
        keeps its team-mates' one-hot ids, so those stay the same; `swimmer-N` has no ids, so
        any length works); MAPPO's centralised critic also fixes the agent count.
        Without `env`, a `module:function` id the checkpoint records is imported only with
        `trust_env_code=True`.
        """
        payload = checkpoint.load(checkpoint_path)
        train = checkpoint.recorded_training(payload)
        model = payload["config"]["model"]
        train.update({key: model[key] for key in ("n_embd", "n_head", "n_block")})
        train["attention_window"] = model.get("attention_window")  # absent before windows
        train.update(faults=dict(faults or {}), init_from=str(checkpoint_path), more_envs=[])
        train.update(options)
        if lr is not None:
            train["lr"] = lr
        algo, trained_env = train.pop("algo"), train.pop("env")
        if env is None:
            envs.check_trusted([trained_env], trust_env_code, str(checkpoint_path))
        env = trained_env if env is None else envs.id_of(env)
        trainer = cls(env, algo, out_dir=out_dir, **train)
        try:
            check_fits(ModelConfig.from_dict(model), trainer.env, env)
            keep = (
                {}
                if reset_optimizer
                else {"params": trainer.params, "optimizer": trainer.optimizer}
            )
            checkpoint.restore_pretrained(
                payload, checkpoint_path, policy=trainer.policy, obs_norm=trainer.obs_norm,
                value_norm=trainer.value_norm, lr=trainer.config.lr, **keep,
            )  # fmt: skip
            if action_std is not None:
                trainer.policy.reset_std(action_std)
        except BaseException:
            trainer.close()
            raise
        return trainer

    def evaluate(self, episodes: int = 10, deterministic: bool = True) -> list[float]:
        """Returns of full episodes of the current policy on this trainer's (changed) robot."""
        from mat_sdk.evaluation import evaluate

        # this run's own env, named to it: nothing read from a file
        loaded = self._as_loaded()
        return evaluate(loaded, episodes, env_id=self.config.env, deterministic=deterministic)

    def _as_loaded(self):
        """This trainer's policy as `mat eval` sees a checkpoint: weights + obs normaliser."""
        from mat_sdk.evaluation import CheckpointPolicy

        norm = self.obs_norm if self.config.normalize_obs else None
        return CheckpointPolicy(self.policy, norm, {"train": asdict(self.config)})

    def close(self) -> None:
        for env in self.envs:
            env.close()
        self.gradients.close()
        if self._remote is not None:
            self._remote.close()

    def __enter__(self) -> Trainer:
        return self

    def __exit__(self, *exc) -> None:
        self.close()
