"""PPO training of MAT (and MAT-Dec, MAPPO, HAPPO) on vectorised multi-agent envs.

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
import os
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import torch

from mat_sdk import envs
from mat_sdk.common import files
from mat_sdk.envs import Env
from mat_sdk.envs.tasks.reward_check import check_reward
from mat_sdk.policy import checkpoint
from mat_sdk.policy.checkpoint import CHECKPOINT_NAME
from mat_sdk.policy.config import TrainConfig
from mat_sdk.policy.model import ModelConfig, PolicyNetwork, build_policy, check_fits
from mat_sdk.policy.normalization import RunningMeanStd, ValueNorm
from mat_sdk.training import happo, joint_update
from mat_sdk.training.flat_params import flat_adam
from mat_sdk.training.gradients import MinibatchGradients
from mat_sdk.training.ppo import Rows
from mat_sdk.training.rollout import RolloutCollector, Trajectory
from mat_sdk.training.run_log import ProgressBar, RunLog, update_metrics


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
        # and the decisions taken for the user, in words
        cfg, self.notes = TrainConfig.for_task(envs.id_of(env), algo, **options)
        self.resumed_with: dict[str, Any] = {}  # how-to-run changes of a resume (`load`)
        self.config = cfg
        self.device = cfg.run.resolve_device()
        torch.manual_seed(cfg.run.seed)
        cfg.run.configure_torch()
        self._remote = None
        if cfg.run.ray is not None:
            from mat_sdk.training.ray_rollouts import RayRollouts

            self._remote = RayRollouts(cfg)
        self.envs = cfg.training_envs(shapes_only=self._remote is not None)
        self.env = self.envs[0]  # the shapes and names: the first env's
        if self.env.reward_terms and not cfg.init_from:  # warn before training, not after
            env = cfg.env
            self.notes += check_reward(env.id, cfg.run.seed, **env.team_options)
        self.model_config = cfg.model_config(self.env)
        self.policy: PolicyNetwork = build_policy(self.model_config).to(self.device)
        self.build_optimizer()
        compile_mode = "default" if cfg.run.compile else None
        self.gradients = MinibatchGradients(
            self.policy, self.params, cfg, cfg.run.update_workers, compile_mode
        )
        self.value_norm = ValueNorm(device=self.device)
        first = RolloutCollector(self.env, self.policy, cfg, self.device)
        self.collectors = [first] + [
            RolloutCollector(env, self.policy, cfg, self.device, share=first)
            for env in self.envs[1:]
        ]
        self.progress = checkpoint.Progress()
        self.out_dir = Path(out_dir) if out_dir is not None else None

    def build_optimizer(self) -> None:
        """Adam over the policy's parameters, laid out flat (`FlatParameters`); MAPPO's
        critic gets its own learning rate when `critic_lr` is set."""
        ppo_config = self.config.ppo
        critic = getattr(self.policy, "critic", None) if ppo_config.critic_lr else None
        actors = list(self.policy.actors) if self.model_config.algorithm.actor_per_agent else None
        self.params, self.optimizer = flat_adam(
            self.policy, ppo_config.lr, ppo_config.adam_eps, critic, ppo_config.critic_lr,
            parts=actors,
        )  # fmt: skip

    # ------------------------------------------------------------------ acting
    @property
    def collector(self) -> RolloutCollector:
        """The collector of the next update: updates take the env ids in turn."""
        return self.collectors[self.progress.updates % len(self.collectors)]

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
        with files.RunLock(self.out_dir) if self.out_dir else contextlib.nullcontext():
            return self._learn(total_steps, callback, progress_bar)

    def _learn(self, total_steps: int, callback, progress_bar: bool) -> Trainer:
        per_update = self.config.ppo.steps_per_update
        checkpoint_every = self.config.run.checkpoint_every
        self.gradients.start()  # the update workers start up during the first rollout
        log = RunLog(self.out_dir, resume_after=self.progress.updates) if self.out_dir else None
        done = self.progress.steps
        bar = ProgressBar(self.planned_steps(total_steps), done, progress_bar)
        try:
            while self.progress.steps < total_steps:
                start = time.perf_counter()
                trajectory = self.rollout()
                rolled = time.perf_counter()
                losses = self._update(trajectory)
                updated = time.perf_counter()
                losses |= {**trajectory.diagnostics(), **self._action_std()}
                self.progress.steps += per_update
                self.progress.updates += 1
                metrics = update_metrics(
                    self.progress, trajectory.finished, trajectory.rewards, losses, per_update,
                    rollout_s=rolled - start, update_s=updated - rolled,
                )  # fmt: skip
                if log:
                    log.write(metrics)
                if self.out_dir and self.progress.updates % checkpoint_every == 0:
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
        per_update = self.config.ppo.steps_per_update
        done = self.progress.steps
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
        """One update (`joint_update`, or HAPPO's agents in turn), refused if it diverged."""
        ppo_config, generator = self.config.ppo, self.collector.shuffle_generator
        rows = trajectory.rows(ppo_config.advantage_std_floor)
        if self.model_config.algorithm.sequential_update:
            losses, finite = happo.update(
                self.policy, self.params, self.optimizer, self.value_norm, rows, ppo_config,
                generator,
            )  # fmt: skip
        else:
            losses, finite = joint_update.update(
                self.params, self.optimizer, self.value_norm, self.gradients, rows, ppo_config,
                generator,
            )  # fmt: skip
        if not finite:
            raise TrainingDiverged(
                f"non-finite loss at update {self.progress.updates + 1}; training stopped, "
                "the last good checkpoint is kept"
            )
        return losses

    def _action_std(self) -> dict[str, float]:
        """The policy's mean action std (continuous actions): how much it still explores."""
        std = self.policy.std()
        return {} if std is None else {"action_std": float(std.detach().mean())}

    def optimizer_step(self, rows: Rows, idx: torch.Tensor):
        """One PPO step on the minibatch `idx` of `rows` (`joint_update.optimizer_step`)."""
        return joint_update.optimizer_step(
            self.params, self.optimizer, self.value_norm, self.gradients, rows, idx,
            self.config.ppo.max_grad_norm,
        )  # fmt: skip

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
        path: str | os.PathLike,
        out_dir: str | Path | None = None,
        **overrides: Any,
    ) -> Trainer:
        """Rebuild a trainer from a checkpoint; `learn` then continues exactly where it stopped.

        Overrides may change how to run (device, workers, update_workers,
        checkpoint_every); any other training option given must be the checkpoint's own
        (`checkpoint.training_options`). `resumed_with` holds what changed.
        A `module:function` env id the checkpoint records is imported only when the caller
        names that same id (`env=`, `more_envs=`: typed by the user in this process) or the
        path is given as `envs.Trusted(path)`: a checkpoint from elsewhere runs no code.
        """
        payload = checkpoint.load(path)
        train, changed = checkpoint.training_options(payload, path, overrides)
        named = [overrides[key] for key in ("env",) if key in overrides]  # the caller's own
        named += list(overrides.get("more_envs", ()))
        recorded = [train["env"], *train["more_envs"]]
        envs.check_trusted(recorded, path, named=named)
        if envs.is_family(train["env"]):  # trained without an identity: keep it so
            train["env_options"] = {"position": None, **train["env_options"]}
        trainer = cls(train.pop("env"), train.pop("algo"), out_dir=out_dir, **train)
        trainer.resumed_with = changed
        try:
            trainer.progress = checkpoint.restore_training(
                payload, path, policy=trainer.policy, params=trainer.params,
                optimizer=trainer.optimizer, collectors=trainer.collectors,
                value_norm=trainer.value_norm, seed=trainer.config.run.seed,
            )  # fmt: skip
        except BaseException:
            trainer.close()
            raise
        return trainer

    @classmethod
    def from_pretrained(
        cls,
        checkpoint_path: str | os.PathLike,
        env: Env | None = None,
        reset_optimizer: bool = True,
        lr: float | None = None,
        out_dir: str | Path | None = None,
        action_std: float | None = None,
        **options: Any,
    ) -> Trainer:
        """A new run that starts from a trained policy, for a changed robot (few-shot).

        Takes the checkpoint's weights, model size, observation normaliser, value
        normaliser and hyperparameters; `env`, `lr` and `options` (any training option,
        e.g. faults, num_envs, seed) change what is trained on and how. Step
        counts start from 0. `reset_optimizer=False` keeps the Adam moments too;
        `action_std` sets a continuous policy's action std afresh (`PolicyNetwork.reset_std`).

        The changed robot must give the same observation and action sizes (a removed agent
        keeps its team-mates' one-hot ids; `swimmer-N` has none, so any length works); a
        centralised critic also fixes the agent count. Without `env`, a `module:function` id
        the checkpoint records is imported only for a path given as `envs.Trusted`.
        """
        payload = checkpoint.load(checkpoint_path)
        changes = {**options, **({} if lr is None else {"lr": lr})}
        train = checkpoint.pretrained_options(payload, checkpoint_path, changes)
        algo, trained_env = train.pop("algo"), train.pop("env")
        if env is None:
            envs.check_trusted([trained_env], checkpoint_path)
        env = trained_env if env is None else envs.id_of(env)
        trainer = cls(env, algo, out_dir=out_dir, **train)
        try:
            check_fits(ModelConfig.from_dict(payload["config"]["model"]), trainer.env, env)
            keep = (
                {}
                if reset_optimizer
                else {"params": trainer.params, "optimizer": trainer.optimizer}
            )
            checkpoint.restore_pretrained(
                payload, checkpoint_path, policy=trainer.policy, obs_norm=trainer.obs_norm,
                value_norm=trainer.value_norm, lr=trainer.config.ppo.lr, **keep,
            )  # fmt: skip
            if action_std is not None:
                trainer.policy.reset_std(action_std)
        except BaseException:
            trainer.close()
            raise
        return trainer

    def evaluate(self, episodes: int = 10, deterministic: bool = True) -> list[float]:
        """Returns of full episodes of the current policy on this trainer's (changed) robot."""
        from mat_sdk.evaluation.episodes import evaluate

        env_id = self.config.env.id  # this run's own, named to it: nothing read from a file
        return evaluate(self._as_loaded(), episodes, env_id=env_id, deterministic=deterministic)

    def _as_loaded(self):
        """This trainer's policy as `mat eval` sees a checkpoint: weights + obs normaliser."""
        from mat_sdk.evaluation.episodes import CheckpointPolicy

        norm = self.obs_norm if self.config.ppo.normalize_obs else None
        return CheckpointPolicy(self.policy, norm, self.config)

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
