"""`RolloutCollector`: a policy acting in vectorised envs, and what PPO learns from it.

    collector = RolloutCollector(env, policy, config)
    trajectory = collector.collect()                     # rollout_length steps of every env
    trajectory = collector.advantages(trajectory, value_norm)  # with GAE and returns
    rows = trajectory.rows(config.ppo.advantage_std_floor)   # the update's rows

The trainer, the Ray rollout workers, the benchmarks and the tests all collect through this
one class. It owns what acting needs: the observation normaliser (updated as observations
arrive), the sampling generator, the agent-order generator, and the envs' next observation.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass
from functools import partial
from typing import Any

import numpy as np
import torch
from torch import Tensor

from mat_sdk.envs import VecTeam
from mat_sdk.policy.config import TrainConfig
from mat_sdk.policy.model import PolicyNetwork, in_agent_order
from mat_sdk.policy.normalization import RunningMeanStd, ValueNorm
from mat_sdk.training.ppo import Rows, gae

STEP_FIELDS = ("obs", "actions", "log_probs", "values", "rewards", "terminated", "done")
MASK_FIELDS = ("order", "active", "available", "action_dims")  # where the envs have them


@dataclass
class Trajectory:
    """One update's data: tensors [T, E, ...] of `rollout_length` steps of every env (rewards
    and the episode flags [T, E, 1 or n, 1]); the masks where the envs have them (`order` when
    shuffling agents; `active`, `available`, `action_dims`: `RolloutCollector.masks`,
    `action_dims`); the values to bootstrap from at truncations and after the last step; the
    returns of the episodes that finished; the raw observations when asked (Ray workers);
    and, once `RolloutCollector.advantages` has run, the advantages and returns."""

    obs: Tensor
    actions: Tensor
    log_probs: Tensor
    values: Tensor
    rewards: Tensor
    terminated: Tensor
    done: Tensor
    bootstrap: Tensor  # [T, E, n, 1]
    last_values: Tensor  # [E, n, 1]
    finished: list[float]
    order: Tensor | None = None
    active: Tensor | None = None
    available: Tensor | None = None
    action_dims: Tensor | None = None
    raw_obs: np.ndarray | None = None
    advantages: Tensor | None = None
    returns: Tensor | None = None
    # the reward of each step by named term, weighted [T, E, terms] (tasks built from terms)
    reward_terms: Tensor | None = None
    term_names: tuple[str, ...] = ()
    # where each env's command curriculum stands at the rollout's end [1, E] (else None)
    command_level: Tensor | None = None

    def rows(self, std_floor: float = 0.0) -> Rows:
        """The update's rows [T * E, ...] of every per-step tensor the update reads, with the
        advantages normalised over all of them (their std floored at `std_floor`)."""
        if self.advantages is None:
            raise ValueError("rows need the advantages: RolloutCollector.advantages first")
        names = [f.name for f in dataclasses.fields(Rows)]
        flat = {k: getattr(self, k).flatten(0, 1) for k in names if getattr(self, k) is not None}
        advantages = flat["advantages"]
        # over the agents in their episode only, as the official code (its active masks)
        counted = advantages if "active" not in flat else advantages[flat["active"] > 0]
        scale = counted.std().clamp_min(std_floor) + 1e-5
        flat["advantages"] = (advantages - counted.mean()) / scale
        return Rows(**flat)

    def diagnostics(self) -> dict[str, float]:
        """What says whether learning can still move: the advantages' spread before they are
        normalised (reward units; near 0, every action looks alike) and the share of the
        returns' variance the value predictions explain (1: exact; <= 0: no better than
        their mean). Over the agents in their episode only."""
        if self.advantages is None:
            raise ValueError("diagnostics need the advantages: RolloutCollector.advantages first")
        advantages, returns = self.advantages, self.returns
        if self.active is not None:
            counted = self.active.expand_as(advantages) > 0
            advantages, returns = advantages[counted], returns[counted]
        returns_var = float(returns.var())
        terms = {}
        if self.reward_terms is not None:  # each term's mean per env step: which term rules
            means = self.reward_terms.mean(dim=(0, 1)).tolist()
            terms = {
                f"reward/{name}": mean for name, mean in zip(self.term_names, means, strict=True)
            }
        if self.command_level is not None:  # is the curriculum moving?
            terms["command_level"] = float(self.command_level.mean())
        return {
            "advantage_std": float(advantages.std()),
            # returns - values are the advantages
            "explained_variance": 1.0 - float(advantages.var()) / returns_var
            if returns_var > 0
            else math.nan,
            **terms,
        }

    @classmethod
    def join(cls, parts: list[Trajectory], device: torch.device) -> Trajectory:
        """Several workers' trajectories of the same steps as one (envs side by side)."""
        joined: dict[str, Any] = {}
        for item in dataclasses.fields(cls):
            values = [getattr(part, item.name) for part in parts]
            if values[0] is None:
                joined[item.name] = None
            elif item.name == "finished":
                joined[item.name] = [r for value in values for r in value]
            elif item.name == "raw_obs":
                joined[item.name] = np.concatenate(values)
            elif item.name == "term_names":
                joined[item.name] = values[0]
            elif item.name == "last_values":
                joined[item.name] = torch.cat(values, dim=0).to(device)
            else:  # [T, E, ...]
                joined[item.name] = torch.cat(values, dim=1).to(device)
        return cls(**joined)


class RolloutCollector:
    """Steps `env` with `policy` for `config.ppo.rollout_length` steps per `collect`."""

    def __init__(
        self,
        env: VecTeam,
        policy: PolicyNetwork,
        config: TrainConfig,
        device: torch.device | str = "cpu",
        seed: int | None = None,
        share: RolloutCollector | None = None,
    ):
        """`share`: act with that collector's normaliser, generators and ONNX actor (one
        policy collecting on several envs, e.g. several agent counts of a family)."""
        self.env, self.policy, self.config = env, policy, config
        self.device = torch.device(device)
        seed = config.run.seed if seed is None else seed
        self.next_obs = env.reset(seed=seed)
        if share is not None:
            self.obs_norm, self.generator = share.obs_norm, share.generator
            self.shuffle_generator, self.onnx_actor = share.shuffle_generator, share.onnx_actor
            return
        self.obs_norm = RunningMeanStd(env.obs_dim)
        self.generator = torch.Generator(self.device).manual_seed(seed)  # action sampling
        # agent orders here, minibatch permutations in the update: one stream, as saved
        self.shuffle_generator = torch.Generator().manual_seed(seed + 1)
        self.onnx_actor = None
        if config.run.rollout_backend == "onnx":
            from mat_sdk.training.onnx_actor import OnnxActor

            self.onnx_actor = OnnxActor(policy)

    def observe(self, obs: np.ndarray, update: bool = False) -> Tensor:
        """Raw observations as the policy's input (normalised; `update`: fold them into the
        running statistics first)."""
        if self.config.ppo.normalize_obs:
            if update:
                self.obs_norm.update(obs)
            obs = self.obs_norm.normalize(obs)
        return torch.as_tensor(obs, dtype=torch.float32, device=self.device)

    def agent_order(self, batch: int) -> Tensor | None:
        """A random decoding order per env (`shuffle_agents`), else None: canonical order."""
        if not self.config.ppo.shuffle_agents:
            return None
        keys = torch.rand(batch, self.env.n_agents, generator=self.shuffle_generator)
        return keys.argsort(dim=1).to(self.device)

    def act(
        self,
        obs: Tensor,
        order: Tensor | None,
        deterministic: bool = False,
        available: Tensor | None = None,
    ):
        """Act in `order` (agents decode in that sequence); results back in canonical order.
        `available` [B, n, choices] masks the choices an agent may not take (discrete)."""
        act = self.policy.act if self.onnx_actor is None else self.onnx_actor.act
        act = partial(act, deterministic=deterministic, generator=self.generator)
        if available is None:
            return in_agent_order(order, act, obs)
        return in_agent_order(order, lambda o, a: act(o, available=a), obs, available)

    def masks(self) -> tuple[Tensor | None, Tensor | None]:
        """The envs' current `active` [E, n, 1] and (discrete) `available` [E, n, choices]
        masks, or None for envs without them (`ArrayTeam.masks`)."""
        if not self.env.masks:
            return None, None
        active = torch.as_tensor(self.env.active(), device=self.device).unsqueeze(-1)
        if self.env.action_type != "discrete":
            return active, None
        return active, torch.as_tensor(self.env.available(), device=self.device)

    def action_dims(self) -> Tensor | None:
        """[n, action_size]: 1 on each agent's own action dimensions, 0 on the padding, when
        agents' continuous action widths differ (else None: nothing to mask)."""
        widths = np.asarray(self.env.action_widths)
        if self.env.action_type == "discrete" or (widths == self.env.action_width).all():
            return None
        dims = np.arange(self.env.action_width)[None, :] < widths[:, None]
        return torch.as_tensor(dims, dtype=torch.float32, device=self.device)

    @torch.no_grad()
    def collect(self, update_norm: bool = True, keep_raw: bool = False) -> Trajectory:
        """`rollout_length` steps of every env with the current policy (`Trajectory`).

        `update_norm`: update the observation statistics as observations arrive.
        `keep_raw`: also keep the raw observations (`raw_obs`), for a learner to fold into
        its own statistics (Ray workers collect with a copy of the learner's).
        """
        cfg, env, device = self.config, self.env, self.device
        T, E, n = cfg.ppo.rollout_length, cfg.ppo.num_envs, env.n_agents
        buffers: dict[str, list] = {name: [] for name in (*STEP_FIELDS, *MASK_FIELDS[:3])}
        terms: list[np.ndarray] = []
        raw = [self.next_obs]
        bootstrap = torch.zeros(T, E, n, 1, device=device)
        finished: list[float] = []
        if self.onnx_actor is not None:
            self.onnx_actor.refresh()
        obs = self.observe(self.next_obs, update=update_norm)
        for t in range(T):
            order = self.agent_order(E)
            active, available = self.masks()
            actions, log_probs, values = self.act(obs, order, available=available)
            next_obs, reward, terminated, truncated, info = env.step(actions.cpu().numpy())
            for name, value in (
                ("obs", obs),
                ("actions", actions),
                ("log_probs", log_probs),
                ("values", values),
                ("order", order),
                ("active", active),
                ("available", available),
            ):
                buffers[name].append(value)
            buffers["rewards"].append(self._flags(reward).view(E, 1, 1))
            if env.reward_terms:
                terms.append(info["reward_terms"])
            # an agent that left the episode ends its own trace there (the team's goes on)
            for name, flags in (("terminated", terminated), ("done", terminated | truncated)):
                flags = self._flags(flags).view(E, 1, 1)
                if "left" in info:
                    flags = torch.maximum(flags, self._flags(info["left"]).view(E, n, 1))
                buffers[name].append(flags)
            if truncated.any():  # bootstrap from the last observation of a time-limited episode
                final = self.observe(info["final_obs"][truncated])
                bootstrap[t, torch.as_tensor(truncated, device=device)] = self.policy.values(final)
            finished += info["episode_return"][info["done"]].tolist()
            levels = info["command_level"]
            self.next_obs = next_obs
            if t < T - 1:
                raw.append(next_obs)
            obs = self.observe(next_obs, update=update_norm and t < T - 1)
        stacked = {
            name: torch.stack(values) if values[0] is not None else None
            for name, values in buffers.items()
        }
        dims = self.action_dims()
        return Trajectory(
            **stacked,
            bootstrap=bootstrap,
            last_values=self.policy.values(obs),
            finished=finished,
            action_dims=None if dims is None else dims.expand(T, E, n, -1),
            raw_obs=np.concatenate(raw) if keep_raw else None,
            reward_terms=torch.as_tensor(np.stack(terms), dtype=torch.float32) if terms else None,
            term_names=tuple(env.reward_terms),
            command_level=None
            if np.isnan(levels).all()
            else torch.as_tensor(levels, dtype=torch.float32).view(1, E),
        )

    def _flags(self, flags: np.ndarray) -> Tensor:
        return torch.as_tensor(flags, dtype=torch.float32, device=self.device)

    def advantages(self, trajectory: Trajectory, value_norm: ValueNorm) -> Trajectory:
        """The trajectory with its advantages (GAE on the shared reward, per agent) and
        returns, from ValueNorm'd values de-normalised."""
        cfg = self.config
        denorm = value_norm.denormalize
        values = denorm(trajectory.values)
        next_values = torch.cat((values[1:], denorm(trajectory.last_values)[None]))
        ended = trajectory.done.expand_as(next_values) > 0
        next_values = torch.where(ended, denorm(trajectory.bootstrap), next_values)
        advantages = gae(
            trajectory.rewards,
            values,
            next_values,
            trajectory.terminated,
            trajectory.done,
            cfg.ppo.gamma,
            cfg.ppo.gae_lambda,
        )
        return dataclasses.replace(trajectory, advantages=advantages, returns=advantages + values)
