"""Rollouts on Ray actors: each worker steps its share of the env copies with the learner's
current policy; the learner (the `Trainer` that owns this) gathers, updates and broadcasts.

    mat train cheetah-6x1 --ray --workers 4            # a local Ray instance
    mat train cheetah-6x1 --ray auto --workers 32      # an existing cluster (`ray start`)

Only imported when `RunConfig.ray` is set, so Ray stays an optional extra
(`pip install 'mat-sdk[ray]'`). Worker k steps env copies `offset_k .. offset_k + share_k`
with the same seeds a local run gives those copies. A worker that dies (its process killed,
its node lost) is replaced by a fresh one, which collects the dead worker's share of the
current update again: no update is lost or shortened.

Workers act with the torch policy, or through ONNX Runtime with
`rollout_backend="onnx"` (`mat_sdk.training.onnx_actor`; faster batched acting).
"""

from __future__ import annotations

import logging
import os
from typing import TYPE_CHECKING, Any

import numpy as np

from mat_sdk.training.rollout import Trajectory

if TYPE_CHECKING:
    from mat_sdk.policy.config import TrainConfig

log = logging.getLogger(__name__)
_REPLACEMENT_SEED_STRIDE = 7919  # a fresh worker's envs must not replay the dead one's


class RolloutWorker:
    """A Ray actor: a rollout collector for its share of the env copies."""

    def __init__(self, config: TrainConfig, offset: int, share: int, generation: int):
        from mat_sdk.policy.model import build_policy
        from mat_sdk.training.rollout import RolloutCollector

        own = config.with_options(
            num_envs=share,
            workers=0,
            update_workers=0,
            device="cpu",
            ray=None,
            seed=config.run.seed + offset + _REPLACEMENT_SEED_STRIDE * generation,
        )
        own.run.configure_torch()
        env = own.make_envs()
        self.collector = RolloutCollector(env, build_policy(own.model_config(env)), own)

    def pid(self) -> int:
        return os.getpid()

    def collect(self, weights: dict, obs_norm: dict) -> Trajectory:
        self.collector.policy.load_state_dict(weights)
        # As in a local run, the observation statistics follow the observations as they
        # arrive; the learner then folds every worker's raw observations into its own.
        self.collector.obs_norm.load_state_dict(obs_norm)
        return self.collector.collect(update_norm=True, keep_raw=True)


def require_ray() -> None:
    """RuntimeError saying how to install Ray, where it is not (before any work starts)."""
    try:
        import ray  # noqa: F401
    except ImportError:
        raise RuntimeError("--ray needs Ray: pip install 'mat-sdk[ray]'") from None


def connect(address: str, cpus: int = 0) -> bool:
    """Join the Ray cluster at `address`, or start a Ray instance here ("local": at least
    `cpus` CPUs, however many cores there are); True when this call started Ray."""
    require_ray()
    import ray

    if ray.is_initialized():
        return False
    local = address in ("", "local")
    ray.init(
        address=None if local else address,
        num_cpus=max(os.cpu_count() or 1, cpus) if local else None,
        object_store_memory=256 * 1024**2 if local else None,
        include_dashboard=False,
        log_to_driver=False,
    )
    return True


class RayRollouts:
    """The learner's handle on its Ray workers."""

    def __init__(self, config):
        import ray

        self.ray = ray
        self._started_ray = connect(config.run.ray, cpus=config.run.workers)
        workers, num_envs = max(1, config.run.workers), config.ppo.num_envs
        if workers > num_envs:
            raise ValueError(f"{workers} Ray workers need at least as many envs, not {num_envs}")
        shares = np.array_split(np.arange(num_envs), workers)
        self._plan = [(int(part[0]), len(part)) for part in shares]
        self._config = config
        self._actor = ray.remote(num_cpus=1, max_restarts=0)(RolloutWorker)
        self.replacements = 0
        self.actors = [self._start(k, generation=0) for k in range(workers)]

    def _start(self, k: int, generation: int):
        offset, share = self._plan[k]
        return self._actor.remote(self._config, offset, share, generation)

    def collect(self, trainer) -> dict[str, Any]:
        """Every worker's trajectories for one update, joined along the env axis."""
        ray = self.ray
        weights = ray.put({k: v.detach().cpu() for k, v in trainer.policy.state_dict().items()})
        obs_norm = ray.put(trainer.obs_norm.state_dict())
        pending = [actor.collect.remote(weights, obs_norm) for actor in self.actors]
        parts = []
        for k, future in enumerate(pending):
            while True:
                try:
                    parts.append(ray.get(future))
                    break
                except ray.exceptions.RayActorError as error:
                    self.replacements += 1
                    log.warning("Ray rollout worker %d died (%s); replacing it", k, error)
                    self.actors[k] = self._start(k, generation=self.replacements)
                    future = self.actors[k].collect.remote(weights, obs_norm)
        return Trajectory.join(parts, trainer.device)

    def close(self) -> None:
        for actor in self.actors:
            self.ray.kill(actor)
        self.actors = []
        if self._started_ray:
            self.ray.shutdown()
