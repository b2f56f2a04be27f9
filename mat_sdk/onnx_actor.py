"""Acting for rollouts through ONNX Runtime (`TrainConfig.rollout_backend = "onnx"`).

Batched acting is where ONNX Runtime beats eager torch most (BENCHMARKS.md, B = 40, n = 6:
~1.3 ms vs ~9.9 ms per control step). Before each rollout the control-step graph is rebuilt
from the current weights (`mat_export.decode_graph`, no `torch.onnx` tracing: ~0.1 s), with
identity normalisers, because the trainer feeds normalised observations and stores
normalised values. Noise comes from the trainer's torch generator, so a seed still fixes the
run; the log-probs of the sampled actions are computed here from the returned distribution.
"""

from __future__ import annotations

import numpy as np
import onnxruntime as ort
import torch

from mat_sdk.model import Policy


class OnnxActor:
    def __init__(self, policy: Policy):
        self.policy = policy
        self.session: ort.InferenceSession | None = None
        self.discrete = policy.cfg.action_type == "discrete"

    def refresh(self) -> None:
        """Rebuild the graph from the policy's current weights."""
        from mat_export.decode_graph import build_decode

        dim = self.policy.cfg.obs_dim
        graph = build_decode(
            self.policy, np.zeros(dim, np.float32), np.ones(dim, np.float32), None, 0.0, 1.0
        )
        options = ort.SessionOptions()
        options.intra_op_num_threads = options.inter_op_num_threads = 1
        options.log_severity_level = 3
        self.session = ort.InferenceSession(
            graph.SerializeToString(), options, providers=["CPUExecutionProvider"]
        )

    def act(self, obs: torch.Tensor, generator: torch.Generator, deterministic: bool = False):
        """Like `Policy.act` on normalised obs [B, n, D]: actions, log-probs, values."""
        shape = (*obs.shape[:2], self.policy.cfg.action_dim)
        if deterministic:
            noise = torch.zeros(shape)
        elif self.discrete:
            uniform = torch.rand(shape, generator=generator).clamp_min(1e-20)
            noise = -torch.log(-torch.log(uniform))
        else:
            noise = torch.randn(shape, generator=generator)
        feed = {"obs": obs.cpu().numpy(), "noise": noise.numpy()}
        if self.discrete:
            feed["available"] = np.ones(shape, np.float32)
            actions, logits, values = self.session.run(["actions", "logits", "values"], feed)
            log_probs = torch.log_softmax(torch.from_numpy(logits), -1)
            log_prob = log_probs.gather(-1, torch.from_numpy(actions).long())
        else:
            actions, mean, std, values = self.session.run(
                ["actions", "mean", "std", "values"], feed
            )
            dist = torch.distributions.Normal(torch.from_numpy(mean), torch.from_numpy(std))
            log_prob = dist.log_prob(torch.from_numpy(actions))
        device = obs.device
        return (
            torch.from_numpy(actions).to(device),
            log_prob.to(device),
            torch.from_numpy(values).to(device),
        )
