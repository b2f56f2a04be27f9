"""A MAT run the way the official code runs it: the baseline of `mat bench train` (an update
step) and `mat bench runtime` (a control step).

Same parameters (and names) as `mat_sdk.policy.model.MAT`, so one state dict drives both, and the
same math, so tests hold their losses, gradients and actions equal. What differs is how it
runs, as in the official `ma_transformer.py` / `transformer_act.py` / `mat_trainer.py`:
attention as explicit matmul + masked softmax against a fixed `tril` buffer, validated
`torch.distributions`, actions chosen by re-running the whole decoder once per agent, the PPO
loss assembled step by step, and torch's default Adam (a for-loop on CPU). Not used for training.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mat_sdk.policy.model import MAT
from mat_sdk.training.ppo import Rows


class OfficialAttention(nn.Module):
    def __init__(self, n_embd: int, n_head: int, n_agent: int, masked: bool):
        super().__init__()
        self.n_head, self.masked = n_head, masked
        self.key = nn.Linear(n_embd, n_embd)
        self.query = nn.Linear(n_embd, n_embd)
        self.value = nn.Linear(n_embd, n_embd)
        self.proj = nn.Linear(n_embd, n_embd)
        self.register_buffer(
            "mask",
            torch.tril(torch.ones(n_agent + 1, n_agent + 1)).view(1, 1, n_agent + 1, n_agent + 1),
        )

    def forward(self, key: Tensor, value: Tensor, query: Tensor) -> Tensor:
        B, L, D = query.size()
        k = self.key(key).view(B, L, self.n_head, D // self.n_head).transpose(1, 2)
        q = self.query(query).view(B, L, self.n_head, D // self.n_head).transpose(1, 2)
        v = self.value(value).view(B, L, self.n_head, D // self.n_head).transpose(1, 2)
        att = (q @ k.transpose(-2, -1)) * (1.0 / math.sqrt(k.size(-1)))
        if self.masked:
            att = att.masked_fill(self.mask[:, :, :L, :L] == 0, float("-inf"))
        att = F.softmax(att, dim=-1)
        y = (att @ v).transpose(1, 2).contiguous().view(B, L, D)
        return self.proj(y)


def _swap_attention(module: nn.Module, n_agent: int) -> None:
    """Replace each of our attention modules by the official one, keeping the weights."""
    for name, child in module.named_children():
        if type(child).__name__ == "Attention":
            official = OfficialAttention(
                child.query.in_features, child.n_head, n_agent, child.causal
            )
            official.load_state_dict(child.state_dict(), strict=False)
            setattr(module, name, official)
        else:
            _swap_attention(child, n_agent)


class OfficialStyleMAT(nn.Module):
    """Our MAT's parameters, run through the official code's forward pass and action loop."""

    def __init__(self, ours: MAT, n_agent: int):
        super().__init__()
        self.ours = ours
        _swap_attention(self.ours, n_agent)

    def encode(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        """The official `Encoder.forward`: representations and values."""
        enc = self.ours.encoder
        x = enc.ln(enc.obs_encoder(obs))
        for block in enc.blocks:
            x = block.ln1(x + block.attn(x, x, x))
            x = block.ln2(x + block.mlp(x))
        return x, enc.head(x)

    def decode(self, shifted: Tensor, rep: Tensor) -> Tensor:
        """The official `Decoder.forward`: action means at every position, causally."""
        dec = self.ours.decoder
        h = dec.ln(dec.action_encoder(shifted))
        for block in dec.blocks:
            h = block.ln1(h + block.attn1(h, h, h))
            h = block.ln2(rep + block.attn2(key=h, value=h, query=rep))
            h = block.ln3(h + block.mlp(h))
        return dec.head(h)

    def std(self) -> Tensor:
        return torch.sigmoid(self.ours.log_std) * 0.5

    def forward(self, obs: Tensor, actions: Tensor):
        rep, values = self.encode(obs)
        return self.decode(self.ours.shift_tokens(actions), rep), self.std(), values

    @torch.no_grad()
    def act(self, obs: Tensor, deterministic: bool = True) -> tuple[Tensor, Tensor, Tensor]:
        """`get_actions` with `continuous_autoregreesive_act`: the whole decoder re-run over all
        n positions once per agent, a validated `Normal` and its log-prob per agent."""
        rep, values = self.encode(obs)
        batch, n, action_size = *obs.shape[:2], self.ours.cfg.action_size
        shifted = obs.new_zeros(batch, n, action_size)
        actions = obs.new_zeros(batch, n, action_size)
        log_probs = torch.zeros_like(actions)
        for i in range(n):
            mean = self.decode(shifted, rep)[:, i, :]
            distri = torch.distributions.Normal(mean, self.std())
            action = mean if deterministic else distri.sample()
            actions[:, i, :] = action
            log_probs[:, i, :] = distri.log_prob(action)
            if i + 1 < n:
                shifted[:, i + 1, :] = action
        return actions, log_probs, values


def official_loss(model: OfficialStyleMAT, value_norm, mb: Rows, cfg) -> Tensor:
    """`mat_trainer.ppo_update` for continuous actions, step by step (with a correct Huber)."""
    mean, std, values = model(mb.obs, mb.actions)
    distri = torch.distributions.Normal(mean, std)  # validate_args on, as the official code runs
    action_log_probs = distri.log_prob(mb.actions)
    dist_entropy = distri.entropy().mean()
    imp_weights = torch.exp(action_log_probs - mb.log_probs)
    surr1 = imp_weights * mb.advantages
    surr2 = torch.clamp(imp_weights, 1.0 - cfg.clip, 1.0 + cfg.clip) * mb.advantages
    policy_loss = -torch.sum(torch.min(surr1, surr2), dim=-1, keepdim=True).mean()
    value_pred_clipped = mb.values + (values - mb.values).clamp(-cfg.clip, cfg.clip)
    value_norm.update(mb.returns)
    error_clipped = value_norm.normalize(mb.returns) - value_pred_clipped
    error_original = value_norm.normalize(mb.returns) - values
    value_loss_clipped = _huber(error_clipped, cfg.huber_delta)
    value_loss_original = _huber(error_original, cfg.huber_delta)
    value_loss = torch.max(value_loss_original, value_loss_clipped).mean()
    return policy_loss - dist_entropy * cfg.entropy_coef + value_loss * cfg.value_coef


def _huber(e: Tensor, d: float) -> Tensor:
    a = (abs(e) <= d).float()
    b = (abs(e) > d).float()
    return a * e**2 / 2 + b * d * (abs(e) - d / 2)
