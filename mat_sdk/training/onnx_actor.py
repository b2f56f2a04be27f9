"""Acting for rollouts through ONNX Runtime (`TrainConfig.rollout_backend = "onnx"`).

Batched acting is where ONNX Runtime beats eager torch most (BENCHMARKS.md). Before each
rollout the control-step graph is rebuilt from the current weights (`mat_sdk.policy.control_graph`,
no `torch.onnx` tracing, so it is quick), with
identity normalisers, because the trainer feeds normalised observations and stores
normalised values. Noise comes from the trainer's torch generator, so a seed still fixes the
run; the log-probs of the sampled actions come from the returned distribution through the
policy's own `ActionDistribution`.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch

from mat_runtime.policy import session
from mat_sdk.policy.model import PolicyNetwork


class OnnxActor:
    def __init__(self, policy: PolicyNetwork):
        self.policy = policy
        self.session: ort.InferenceSession | None = None
        self.discrete = policy.cfg.action_type == "discrete"

    def refresh(self) -> None:
        """Rebuild the graph from the policy's current weights."""
        from mat_sdk.policy.control_graph import build_decode

        dim = self.policy.cfg.obs_dim
        graph = build_decode(
            self.policy, np.zeros(dim, np.float32), np.ones(dim, np.float32), None, 0.0, 1.0
        )
        self.session = session(graph.SerializeToString(), batched=True)  # num_envs rows

    def act(
        self,
        obs: torch.Tensor,
        generator: torch.Generator,
        deterministic: bool = False,
        available: torch.Tensor | None = None,
    ):
        """Like `PolicyNetwork.act` on normalised obs [B, n, D]: actions, log-probs, values."""
        shape = (*obs.shape[:2], self.policy.cfg.action_size)
        noise = torch.zeros(shape) if deterministic else self.policy.dist.noise(shape, generator)
        feed = {"obs": obs.cpu().numpy(), "noise": noise.numpy()}
        if self.discrete:
            ones = np.ones(shape, np.float32)
            feed["available"] = ones if available is None else available.cpu().numpy()
        head = ["logits"] if self.discrete else ["mean", "std"]
        outputs = self.session.run(["actions", *head, "values"], feed)
        actions, *params, values = (torch.from_numpy(out) for out in outputs)
        dist = self.policy.dist.make(params[0], params[1] if len(params) > 1 else None, None)
        # (the graph's logits are already masked: unavailable choices get UNAVAILABLE_LOGIT)
        log_prob = self.policy.dist.log_prob_entropy(dist, actions)[0]
        device = obs.device
        return actions.to(device), log_prob.to(device), values.to(device)
