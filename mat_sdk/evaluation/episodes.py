"""Evaluate a trained policy: episode returns on a (possibly changed) robot, optional video."""

from __future__ import annotations

import os
from collections.abc import Iterator, Mapping
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import torch

from mat_sdk import envs
from mat_sdk.policy import checkpoint
from mat_sdk.policy.config import TrainConfig
from mat_sdk.policy.model import PolicyNetwork, check_fits
from mat_sdk.policy.normalization import RunningMeanStd

VIDEO_SUFFIXES = (".mp4", ".gif")  # what write_video's imageio writers produce
VIDEO_FPS = 30  # frames rendered per simulated second (a 50 Hz robot: every other step)


@dataclass
class CheckpointPolicy:
    """A checkpoint's policy with the observation normaliser it was trained with."""

    policy: PolicyNetwork
    obs_norm: RunningMeanStd | None
    training: TrainConfig  # how it was trained: its env, faults and options among it
    # where the policy came from, for messages; given as `envs.Trusted`, the user vouched
    # for it: a `module:function` env id it records may be imported to evaluate it
    source: str | os.PathLike = "the checkpoint"

    @classmethod
    def from_checkpoint(cls, path: str | os.PathLike) -> CheckpointPolicy:
        """The policy a checkpoint holds; `envs.Trusted(path)`: the user's word that the env
        code it names may run (its `module:function` id imported when evaluating on it)."""
        payload = checkpoint.load(path)
        policy, norm = checkpoint.restore_policy(payload, path)
        training = checkpoint.recorded_config(payload)
        return cls(policy, norm, training, path)

    def predict(self, obs, team, deterministic: bool = True, generator=None, available=None):
        """Actions for raw observations of `team` (an env with its agents and sizes): an
        array [n, obs_dim] or [B, n, obs_dim] -> an array [.., n, action_width] (discrete:
        [.., n, 1] choice indices); or a PettingZoo obs dict {agent: obs} -> an action dict
        ready for `env.step` (each agent's own action width; discrete: an int). `available`
        ([.., n, choices], discrete) masks the choices an agent may not take."""
        if isinstance(obs, Mapping):
            agents = list(team.agents)
            if set(obs) != set(agents):
                raise ValueError(
                    f"obs must have one entry per agent of {team.env_id}: {agents}; got {list(obs)}"
                )
            stacked = np.stack([np.asarray(obs[a]) for a in agents])
            actions = self.predict(stacked, team, deterministic, generator, available)
            if team.action_type == "discrete":
                return {a: int(actions[i, 0]) for i, a in enumerate(agents)}
            return {a: actions[i, : team.action_widths[i]] for i, a in enumerate(agents)}
        obs = np.asarray(obs, dtype=np.float32)
        single = obs.ndim == 2
        batch = obs[None] if single else obs
        if batch.ndim != 3 or batch.shape[-1] != team.obs_dim:
            raise ValueError(
                f"obs must be [n, {team.obs_dim}] or [B, n, {team.obs_dim}], got {obs.shape}"
            )
        if available is not None and single:
            available = np.asarray(available)[None]
        actions = self.act(batch, deterministic, generator, available)
        return actions[0] if single else actions

    def act(
        self, obs: np.ndarray, deterministic: bool = True, generator=None, available=None
    ) -> np.ndarray:
        """Raw observations [B, n, obs_dim] -> actions [B, n, A or 1] (numpy); `available`
        [B, n, choices] masks the choices an agent may not take (discrete)."""
        if self.obs_norm is not None:
            obs = self.obs_norm.normalize(obs)
        device = next(self.policy.parameters()).device
        tensor = torch.as_tensor(obs, dtype=torch.float32, device=device)
        if generator is not None and generator.device != device:
            generator = None  # a CPU generator cannot drive CUDA sampling
        if available is not None:
            available = torch.as_tensor(available, dtype=torch.float32, device=device)
        actions, _, _ = self.policy.act(
            tensor, available, deterministic=deterministic, generator=generator
        )
        return actions.cpu().numpy()


@dataclass
class Episodes:
    """Full episodes of a policy: per episode its return, length, whether it ended early (a
    termination such as a fall, not the time limit) and, for a robot with a floating base,
    its mean forward speed (m/s along the start heading, which a turning robot covers less
    of; NaN otherwise) and its velocity in its own heading's frame (`tracking`)."""

    returns: list[float]
    lengths: list[int]
    ended: list[bool]
    speeds: list[float]
    # a reward built from named terms: each term's mean per step over these episodes
    terms: dict[str, float] = field(default_factory=dict)
    # a floating base's mean (vx, vy, yaw rate) per episode after its first second, in its
    # heading's frame (`ArrayTeam.tracking`; NaN otherwise)
    tracking: list[list[float]] = field(default_factory=list)

    def breakdown(self) -> str:
        """Each reward term's mean per step and its share of all terms' magnitude (penalties
        negative): which term rules the reward. Empty for a reward without named terms."""
        if not self.terms:
            return ""
        magnitude = sum(abs(v) for v in self.terms.values()) or 1.0
        width = max(map(len, self.terms))
        lines = [f"{'reward term':<{width}}  per step    share"]
        for name, mean in sorted(self.terms.items(), key=lambda item: -abs(item[1])):
            lines.append(f"{name:<{width}}  {mean:+9.4f}  {100 * mean / magnitude:+6.1f} %")
        lines.append(f"{'total':<{width}}  {sum(self.terms.values()):+9.4f}")
        return "\n".join(lines)

    def summary(self) -> str:
        """One line: return mean +- std, early ends, mean speed where there is one."""
        line = (
            f"return {np.mean(self.returns):.2f} +- {np.std(self.returns):.2f} over "
            f"{len(self.returns)} episodes"
        )
        if any(self.ended):
            early = [n for n, ended in zip(self.lengths, self.ended, strict=True) if ended]
            line += (
                f"; {len(early)} ended early (fell or failed), after {np.mean(early):.0f} "
                "steps on average"
            )
        if not np.isnan(self.speeds).all():
            line += (
                f"; forward speed {np.nanmean(self.speeds):.3f} +- {np.nanstd(self.speeds):.3f} m/s"
            )
        moving = np.array(self.tracking, dtype=float).reshape(-1, 3)
        if len(moving) and not np.isnan(moving).all():  # the heading's frame, after 1 s
            vx, vy, yaw = np.nanmean(moving, axis=0)
            line += (
                f"; in its heading's frame vx {vx:.3f} +- {np.nanstd(moving[:, 0]):.3f} m/s, "
                f"vy {vy:+.3f} m/s, yaw rate {yaw:+.3f} rad/s"
            )
        return line


# The first env seed of an evaluation: far from the training seeds (0, 1, 2, ...), so an
# evaluation's episodes are not its training's.
EVALUATION_SEED = 10_000


@contextmanager
def one_torch_thread() -> Iterator[None]:
    """Act on one torch thread, as the trainer does: a control step's matrices are too small to
    share, and torch's default pool (a thread per core) stalls whenever other processes hold
    the cores."""
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(threads)


def evaluate(
    loaded: CheckpointPolicy,
    episodes: int = 10,
    env_id: str | None = None,
    deterministic: bool = True,
    seed: int = EVALUATION_SEED,
    video: str | Path | None = None,
    **env_options: Any,
) -> list[float]:
    """Returns of `episodes` full episodes (`evaluate_episodes`)."""
    return evaluate_episodes(
        loaded, episodes, env_id, deterministic, seed, video, **env_options
    ).returns


def evaluate_episodes(
    loaded: CheckpointPolicy,
    episodes: int = 10,
    env_id: str | None = None,
    deterministic: bool = True,
    seed: int = EVALUATION_SEED,
    video: str | Path | None = None,
    **env_options: Any,
) -> Episodes:
    """`episodes` full episodes, one per env copy, each copy's first episode; `env_options`
    override the trained env's (e.g. a robot's fixed `command`, other `faults`).

    Without `env_id`, the env the policy was trained on; a `module:function` id that the
    checkpoint records is imported only if the user trusted it (`from_checkpoint`)."""
    trained = loaded.training.env
    if env_id is None:
        envs.check_trusted([trained.id], loaded.source)
    env_id = env_id or trained.id
    options = {**trained.team_options, **env_options}
    if episodes < 1:
        raise ValueError(f"episodes must be >= 1, got {episodes}")
    if video is not None and Path(video).suffix.lower() not in VIDEO_SUFFIXES:
        raise ValueError(f"video {video}: name a {' / '.join(VIDEO_SUFFIXES)} file")
    generator = torch.Generator().manual_seed(seed)
    with (
        one_torch_thread(),
        envs.make_vec(env_id, episodes, seed=seed, **options) as vec,
    ):
        check_fits(loaded.policy.cfg, vec, env_id)
        obs = vec.reset(seed=seed)
        returns, travel = np.full(episodes, np.nan), np.full(episodes, np.nan)
        tracking = np.full((episodes, 3), np.nan)
        term_sums, term_steps = np.zeros(len(vec.reward_terms)), 0
        lengths, ended = np.zeros(episodes, dtype=np.int64), np.zeros(episodes, dtype=bool)
        frames, recorded = [], 0
        recorder = None
        if video:  # env 0's episode again, on a copy with the model's visual assets
            recorder = envs.make_team(env_id, seed=seed, visual=True, **options)
            recorder.reset(seed=seed)
            stride = max(1, round(1 / (recorder.control_timestep * VIDEO_FPS)))
        while np.isnan(returns).any():
            available = vec.available() if vec.action_type == "discrete" else None
            actions = loaded.act(obs, deterministic, generator, available)
            if recorder is not None and recorded < recorder.episode_limit:
                if recorded % stride == 0:  # frames at the video's rate, not every step
                    frames.append(recorder.render())
                recorder.step(actions[0])
                recorded += 1
            running = np.isnan(returns)  # each copy counts its first episode only
            obs, _, terminated, _, info = vec.step(actions)
            term_sums += info["reward_terms"][running].sum(axis=0)
            term_steps += int(running.sum())
            first = info["done"] & np.isnan(returns)
            returns[first] = info["episode_return"][first]
            lengths[first], ended[first] = info["episode_length"][first], terminated[first]
            travel[first] = info["episode_travel"][first]
            tracking[first] = info["episode_tracking"][first]
        timestep = vec.control_timestep
    if video:
        write_video(frames, video, fps=round(1 / (recorder.control_timestep * stride)))
    speeds = travel / np.maximum(lengths * timestep, 1e-9)
    terms = dict(zip(vec.reward_terms, (term_sums / max(term_steps, 1)).tolist(), strict=True))
    return Episodes(
        returns.tolist(), lengths.tolist(), ended.tolist(), speeds.tolist(), terms,
        tracking.tolist(),
    )  # fmt: skip


def write_video(frames: list[np.ndarray], path: str | Path, fps: int = 30) -> Path:
    import imageio.v2 as imageio

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    imageio.mimwrite(path, frames, fps=min(fps, 60), macro_block_size=1)
    return path


def random_team_return(env_id: str, episodes: int = 16, seed: int = 100, **options) -> float:
    """Mean episode return of uniformly random actions (discrete: random available choices),
    one episode per env copy, copy i seeded `seed + i`."""
    rng = np.random.default_rng(0)
    returns: list[float] = []
    with envs.make_vec(env_id, episodes, seed=seed, **options) as vec:
        vec.reset(seed=seed)
        shape = (episodes, vec.n_agents, vec.action_width)
        while len(returns) < episodes:
            if vec.action_type == "discrete":
                available = vec.available() if vec.masks else np.ones((*shape[:2], vec.action_size))
                scores = rng.random(available.shape) * available
                actions = scores.argmax(-1)[..., None].astype(float)
            else:
                actions = rng.uniform(-1, 1, shape)
            _, _, _, _, info = vec.step(actions)
            returns += info["episode_return"][info["done"]].tolist()
    return float(np.mean(returns))
