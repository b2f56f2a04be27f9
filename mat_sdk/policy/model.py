"""Multi-Agent Transformer (Wen et al., 2022) and the baselines it is compared with.

MAT: an encoder reads every agent's observation (unmasked self-attention, a value per
agent); a decoder emits actions one agent at a time, each conditioned on the actions already
chosen. Layer layout, initialisation and the policy's std follow the official code
(docs/ALGORITHM.md): post-LN blocks; the decoder's second attention takes its query from the
encoder representation and its keys/values from the causal action stream.

Rollouts decode with a KV cache (`decode_step`): each decoder block keeps two caches, one per
attention that reads the action stream, so a control step costs O(n) decoder work.

`attention_window` (None: the paper's full attention) lets every attention see only the agents
fewer than W places away in the team's order (the decoder's: the W - 1 before an agent and
itself). A whole control step then costs O(n W) instead of O(n^2), and its caches hold W
entries, which is what serves a thousand agents in linear time and memory; on a chain robot it
also makes what an agent's encoding sees the same whatever the chain's length.

MAT-Dec shares MAT's encoder/critic but acts with one shared MLP per agent on its own
observation; MAPPO pairs a shared MLP actor with a centralised MLP critic; HAPPO gives each
agent its own actor. All four expose `evaluate_actions` (teacher-forced, for PPO) and `act`
(sampling, for rollouts).
"""

from __future__ import annotations

import math
from dataclasses import MISSING, asdict, dataclass, fields

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from mat_sdk.policy.algorithms import Algorithm, algorithm

ACTION_TYPES = ("continuous", "discrete")
UNAVAILABLE_LOGIT = -1e10


def permute_agents(x: Tensor, order: Tensor) -> Tensor:
    """x [B, n, ...] reordered along agents by order [B, n]."""
    index = order.view(*order.shape, *([1] * (x.dim() - 2))).expand_as(x)
    return x.gather(1, index)


def in_agent_order(order: Tensor | None, fn, *inputs: Tensor) -> tuple:
    """`fn(*inputs)` with the agents of every input [B, n, ...] taken in `order` [B, n] (None:
    as they are); its outputs come back in canonical agent order."""
    if order is None:
        return fn(*inputs)
    inverse = order.argsort(dim=1)
    results = fn(*(permute_agents(x, order) for x in inputs))
    return tuple(permute_agents(r, inverse) for r in results)


CHECKPOINT_KEYS = {"action_size": "action_dim"}  # field -> its key in a checkpoint


@dataclass
class ModelConfig:
    obs_dim: int
    action_size: int  # continuous: size of the action vector; discrete: number of choices
    n_agents: int  # agents seen in training (MAPPO's and HAPPO's are tied to it; MAT is not)
    algo: str = "mat"
    action_type: str = "continuous"
    n_embd: int = 64
    n_head: int = 1
    n_block: int = 1
    attention_window: int | None = None  # None: full attention (the paper's)

    def __post_init__(self):
        for name in ("obs_dim", "action_size", "n_agents", "n_embd", "n_head", "n_block"):
            value = getattr(self, name)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise ValueError(f"model {name} must be an integer >= 1, got {value!r}")
        window = self.attention_window
        if window is not None and (
            isinstance(window, bool) or not isinstance(window, int) or window < 2
        ):
            raise ValueError(
                f"model attention_window must be an integer >= 2 or None, got {window!r}"
            )
        algorithm(self.algo)  # a known name, or ValueError listing them
        if self.action_type not in ACTION_TYPES:
            raise ValueError(f"action_type must be one of {ACTION_TYPES}, got {self.action_type!r}")
        if self.n_embd % self.n_head:
            raise ValueError(f"n_embd {self.n_embd} must be divisible by n_head {self.n_head}")

    @property
    def algorithm(self) -> Algorithm:
        """What the algorithm does differently (`mat_sdk.policy.algorithms`)."""
        return algorithm(self.algo)

    @property
    def fixed_team(self) -> bool:
        """Whether the policy acts for exactly `n_agents` agents (a joint-observation critic,
        or HAPPO's actor per agent)."""
        return algorithm(self.algo).centralised_critic

    def to_dict(self) -> dict:
        """As a checkpoint stores it (`CHECKPOINT_KEYS`: the names checkpoints have always
        used, so files written before a rename still load)."""
        return {CHECKPOINT_KEYS.get(k, k): v for k, v in asdict(self).items()}

    @classmethod
    def from_dict(cls, values: dict) -> ModelConfig:
        """From `to_dict`'s output (a checkpoint's), refusing a missing or unknown field."""
        if not isinstance(values, dict):
            raise ValueError(f"the model config must be a mapping, got {type(values).__name__}")
        stored = {stored: name for name, stored in CHECKPOINT_KEYS.items()}
        values = {stored.get(k, k): v for k, v in values.items()}
        names = {f.name for f in fields(cls)}
        required = {f.name for f in fields(cls) if f.default is MISSING}
        unknown, missing = sorted(set(values) - names), sorted(required - set(values))
        if unknown or missing:
            raise ValueError(
                f"model config: unknown field(s) {unknown}, missing {missing}"
                if unknown
                else f"model config: missing field(s) {missing}"
            )
        return cls(**values)


def init_linear(layer: nn.Linear, activated: bool = False, gain: float = 0.01) -> nn.Linear:
    """Official init: orthogonal weights, zero bias; gain 0.01, or ReLU's before an activation."""
    nn.init.orthogonal_(layer.weight, nn.init.calculate_gain("relu") if activated else gain)
    if layer.bias is not None:
        nn.init.zeros_(layer.bias)
    return layer


def mlp_block(n_embd: int) -> nn.Sequential:
    return nn.Sequential(
        init_linear(nn.Linear(n_embd, n_embd), activated=True),
        nn.GELU(),
        init_linear(nn.Linear(n_embd, n_embd)),
    )


def head(n_embd: int, out: int) -> nn.Sequential:
    return nn.Sequential(
        init_linear(nn.Linear(n_embd, n_embd), activated=True),
        nn.GELU(),
        nn.LayerNorm(n_embd),
        init_linear(nn.Linear(n_embd, out)),
    )


KV = tuple[Tensor, Tensor]


def band(length: int, window: int, causal: bool, device=None) -> Tensor:
    """[L, L] bool, True where query i may attend to key j: |i - j| < window (causal: and
    j <= i)."""
    index = torch.arange(length, device=device)
    offset = index[:, None] - index[None, :]
    allowed = offset.abs() < window
    return allowed & (offset >= 0) if causal else allowed


class Attention(nn.Module):
    """Multi-head attention; `causal` masks keys after each query's own position, `window`
    (None: no limit) keys `window` or more places away.

    With `past` (a cached step) the single new query sees every cached key plus its own (the
    last `window` of them), which is exactly its row in the teacher-forced pass; the returned
    cache keeps only those, so it never outgrows the window.
    """

    def __init__(self, n_embd: int, n_head: int, causal: bool, window: int | None = None):
        super().__init__()
        self.n_head, self.causal, self.window = n_head, causal, window
        self.query = init_linear(nn.Linear(n_embd, n_embd))
        self.key = init_linear(nn.Linear(n_embd, n_embd))
        self.value = init_linear(nn.Linear(n_embd, n_embd))
        self.proj = init_linear(nn.Linear(n_embd, n_embd))

    def _heads(self, x: Tensor) -> Tensor:  # [B, L, C] -> [B, H, L, C/H]
        batch, length, width = x.shape
        return x.view(batch, length, self.n_head, width // self.n_head).transpose(1, 2)

    def forward(self, query: Tensor, stream: Tensor, past: KV | None = None) -> tuple[Tensor, KV]:
        q, k, v = (
            self._heads(self.query(query)),
            self._heads(self.key(stream)),
            self._heads(self.value(stream)),
        )
        mask = None
        if past is not None:
            k, v = torch.cat((past[0], k), dim=2), torch.cat((past[1], v), dim=2)
            if self.window is not None:
                k, v = k[:, :, -self.window :], v[:, :, -self.window :]
        elif self.window is not None:
            mask = band(q.shape[2], self.window, self.causal, q.device)
        causal = self.causal and past is None and mask is None
        y = F.scaled_dot_product_attention(q, k, v, attn_mask=mask, is_causal=causal)
        batch, _, length, _ = y.shape
        return self.proj(y.transpose(1, 2).reshape(batch, length, -1)), (k, v)


class EncodeBlock(nn.Module):
    def __init__(self, n_embd: int, n_head: int, window: int | None = None):
        super().__init__()
        self.attn = Attention(n_embd, n_head, causal=False, window=window)
        self.ln1, self.ln2 = nn.LayerNorm(n_embd), nn.LayerNorm(n_embd)
        self.mlp = mlp_block(n_embd)

    def forward(self, x: Tensor) -> Tensor:
        x = self.ln1(x + self.attn(x, x)[0])
        return self.ln2(x + self.mlp(x))


class DecodeBlock(nn.Module):
    """x = ln1(x + attn1(x)); x = ln2(rep + attn2(q=rep, kv=x)); x = ln3(x + mlp(x)).

    Both attentions are causal over the action stream."""

    def __init__(self, n_embd: int, n_head: int, window: int | None = None):
        super().__init__()
        self.attn1 = Attention(n_embd, n_head, causal=True, window=window)
        self.attn2 = Attention(n_embd, n_head, causal=True, window=window)
        self.ln1, self.ln2, self.ln3 = (
            nn.LayerNorm(n_embd),
            nn.LayerNorm(n_embd),
            nn.LayerNorm(n_embd),
        )
        self.mlp = mlp_block(n_embd)

    def forward(self, x: Tensor, rep: Tensor, past: tuple[KV, KV] | None = None):
        attended, kv1 = self.attn1(x, x, None if past is None else past[0])
        x = self.ln1(x + attended)
        attended, kv2 = self.attn2(rep, x, None if past is None else past[1])
        x = self.ln2(rep + attended)
        return self.ln3(x + self.mlp(x)), (kv1, kv2)


class Encoder(nn.Module):
    """Observations [B, n, obs] -> representations [B, n, C] and values [B, n, 1]."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.obs_encoder = nn.Sequential(
            nn.LayerNorm(cfg.obs_dim),
            init_linear(nn.Linear(cfg.obs_dim, cfg.n_embd), activated=True),
            nn.GELU(),
        )
        self.ln = nn.LayerNorm(cfg.n_embd)
        self.blocks = nn.Sequential(
            *(EncodeBlock(cfg.n_embd, cfg.n_head, cfg.attention_window) for _ in range(cfg.n_block))
        )
        self.head = head(cfg.n_embd, 1)

    def forward(self, obs: Tensor) -> tuple[Tensor, Tensor]:
        rep = self.blocks(self.ln(self.obs_encoder(obs)))
        return rep, self.head(rep)


class Decoder(nn.Module):
    """Shifted action tokens [B, L, token] + representations [B, L, C] -> action parameters."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        discrete = cfg.action_type == "discrete"
        self.token_dim = cfg.action_size + 1 if discrete else cfg.action_size
        self.action_encoder = nn.Sequential(
            init_linear(nn.Linear(self.token_dim, cfg.n_embd, bias=not discrete), activated=True),
            nn.GELU(),
        )
        self.ln = nn.LayerNorm(cfg.n_embd)
        self.blocks = nn.ModuleList(
            DecodeBlock(cfg.n_embd, cfg.n_head, cfg.attention_window) for _ in range(cfg.n_block)
        )
        self.head = head(cfg.n_embd, cfg.action_size)

    def forward(self, tokens: Tensor, rep: Tensor) -> Tensor:
        x = self.ln(self.action_encoder(tokens))
        for block in self.blocks:
            x, _ = block(x, rep)
        return self.head(x)

    def step(self, token: Tensor, rep: Tensor, past: list[tuple[KV, KV]] | None):
        """One agent: token [B, 1, token], rep [B, 1, C], caches of the agents before it."""
        x = self.ln(self.action_encoder(token))
        present = []
        for i, block in enumerate(self.blocks):
            x, kv = block(x, rep, None if past is None else past[i])
            present.append(kv)
        return self.head(x), present


class ActionDistribution:
    """Gaussian (state-independent std) or Categorical (with unavailable actions masked)."""

    def __init__(self, action_type: str):
        self.discrete = action_type == "discrete"

    def make(self, params: Tensor, std: Tensor | None, available: Tensor | None):
        if self.discrete:
            if available is not None:
                params = params.masked_fill(available == 0, UNAVAILABLE_LOGIT)
            return torch.distributions.Categorical(logits=params, validate_args=False)
        return torch.distributions.Normal(params, std.expand_as(params), validate_args=False)

    def log_prob_entropy(self, dist, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Per agent and (continuous) per action dimension, as the official PPO ratio uses them."""
        if self.discrete:
            return dist.log_prob(actions.squeeze(-1).long()).unsqueeze(
                -1
            ), dist.entropy().unsqueeze(-1)
        return dist.log_prob(actions), dist.entropy()

    def noise(self, shape, generator: torch.Generator | None, device=None) -> Tensor:
        """Sampling noise: Gumbel (discrete: argmax(logits + it)) or standard normal
        (continuous: mean + std * it)."""
        if self.discrete:
            uniform = torch.rand(shape, generator=generator, device=device)
            return -torch.log(-torch.log(uniform.clamp_min(1e-20)))
        return torch.randn(shape, generator=generator, device=device)

    def sample(self, dist, deterministic: bool, generator: torch.Generator | None) -> Tensor:
        if self.discrete:
            # Choices travel as float indices, so one buffer serves both action types.
            if deterministic:
                return dist.logits.argmax(-1, keepdim=True).float()
            gumbel = self.noise(dist.logits.shape, generator, dist.logits.device)
            return (dist.logits + gumbel).argmax(-1, keepdim=True).float()
        if deterministic:
            return dist.mean
        noise = self.noise(dist.mean.shape, generator, dist.mean.device)
        return dist.mean + dist.stddev * noise


def official_std(log_std: Tensor) -> Tensor:
    """The official parametrisation of the action std: sigmoid(log_std) * 0.5 (initially
    ~0.37)."""
    return torch.sigmoid(log_std) * 0.5


MAX_STD = 0.5  # `official_std`'s bound


def official_log_std(std: float) -> float:
    """The `log_std` that `official_std` maps to `std` (0 < std < 0.5)."""
    return math.log(2 * std / (1 - 2 * std))


class PolicyNetwork(nn.Module):
    """The interface the trainer uses: teacher-forced `evaluate`, sampling `act`."""

    shared_std = True  # one action std for every agent (HAPPO: one per agent's actor)

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.cfg = cfg
        self.dist = ActionDistribution(cfg.action_type)
        if cfg.action_type == "continuous" and self.shared_std:
            self.log_std = nn.Parameter(torch.ones(cfg.action_size))

    def std(self) -> Tensor | None:
        return official_std(self.log_std) if self.cfg.action_type == "continuous" else None

    def reset_std(self, std: float) -> None:
        """Set every agent's action std to `std`: fine-tuning re-opens the exploration that
        training closed, to find a new gait rather than tune the old one."""
        if self.cfg.action_type != "continuous":
            raise ValueError("an action std is for continuous actions; this policy's are discrete")
        if isinstance(std, bool) or not isinstance(std, int | float) or not 0 < std < MAX_STD:
            raise ValueError(f"the action std must be in (0, {MAX_STD}), got {std!r}")
        with torch.no_grad():
            for name, parameter in self.named_parameters():
                if name.split(".")[-1] == "log_std":
                    parameter.fill_(official_log_std(std))

    def values(self, obs: Tensor) -> Tensor:
        raise NotImplementedError

    def action_params(self, obs: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        """Teacher-forced: (mean or logits [B, n, A], values [B, n, 1])."""
        raise NotImplementedError

    def evaluate_actions(self, obs: Tensor, actions: Tensor, available: Tensor | None = None):
        """log-probs and entropies [B, n, A or 1] and values [B, n, 1] of taken actions."""
        params, values = self.action_params(obs, actions)
        dist = self.dist.make(params, self.std(), available)
        log_prob, entropy = self.dist.log_prob_entropy(dist, actions)
        return log_prob, entropy, values

    @torch.no_grad()
    def act(
        self,
        obs: Tensor,
        available: Tensor | None = None,
        deterministic: bool = False,
        generator: torch.Generator | None = None,
    ) -> tuple[Tensor, Tensor, Tensor]:
        """Sample actions [B, n, A or 1]; returns actions, their log-probs and values."""
        raise NotImplementedError


class MAT(PolicyNetwork):
    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        self.encoder = Encoder(cfg)
        self.decoder = Decoder(cfg)

    def values(self, obs: Tensor) -> Tensor:
        return self.encoder(obs)[1]

    def start_token(self, batch: int, device=None) -> Tensor:
        """The first agent's token [B, 1, token]: zeros (continuous) or the one-hot start slot
        [1, 0, ...] (discrete), as in the official code."""
        token = torch.zeros(batch, 1, self.decoder.token_dim, device=device)
        if self.cfg.action_type == "discrete":
            token[:, 0, 0] = 1.0
        return token

    def shift_tokens(self, actions: Tensor) -> Tensor:
        """The decoder's input: a start token, then each agent's predecessor's action."""
        batch = actions.shape[0]
        start = self.start_token(batch, actions.device)
        return torch.cat((start, self.action_token(actions[:, :-1])), dim=1)

    def action_params(self, obs: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        rep, values = self.encoder(obs)
        return self.decoder(self.shift_tokens(actions), rep), values

    def action_token(self, action: Tensor) -> Tensor:
        """Tokens [B, L, token] that agents' actions [B, L, A or 1] become for the next agents."""
        if self.cfg.action_type == "discrete":
            return F.pad(
                F.one_hot(action[..., 0].long(), self.cfg.action_size).to(torch.float32), (1, 0)
            )
        return action

    def decode_step(self, token: Tensor, rep: Tensor, past=None):
        """KV-cached single-agent decoder step: (mean or logits [B, 1, A], present caches)."""
        return self.decoder.step(token, rep, past)

    def decode(self, rep: Tensor, choose) -> tuple[Tensor, Tensor]:
        """The autoregressive loop, KV-cached: each agent's action parameters from the
        actions chosen before it. `choose(i, params)` picks agent i's action [B, 1, A or 1]
        from its parameters [B, 1, A]; returns all actions and parameters [B, n, ...]."""
        token, past = self.start_token(rep.shape[0], rep.device), None
        actions, all_params = [], []
        for i in range(rep.shape[1]):
            params, past = self.decode_step(token, rep[:, i : i + 1], past)
            action = choose(i, params)
            actions.append(action)
            all_params.append(params)
            token = self.action_token(action)
        return torch.cat(actions, 1), torch.cat(all_params, 1)

    @torch.no_grad()
    def act(self, obs, available=None, deterministic=False, generator=None):
        rep, values = self.encoder(obs)
        std, log_probs = self.std(), []

        def sample(i: int, params: Tensor) -> Tensor:
            mask = None if available is None else available[:, i : i + 1]
            dist = self.dist.make(params, std, mask)
            action = self.dist.sample(dist, deterministic, generator)
            log_probs.append(self.dist.log_prob_entropy(dist, action)[0])
            return action

        actions, _ = self.decode(rep, sample)
        return actions, torch.cat(log_probs, 1), values


def actor_mlp(obs_dim: int, n_embd: int, out: int) -> nn.Sequential:
    """The official MAT-Dec actor: LN -> Linear -> GELU -> LN -> Linear -> GELU -> LN -> Linear."""
    return nn.Sequential(
        nn.LayerNorm(obs_dim),
        init_linear(nn.Linear(obs_dim, n_embd), activated=True),
        nn.GELU(),
        nn.LayerNorm(n_embd),
        init_linear(nn.Linear(n_embd, n_embd), activated=True),
        nn.GELU(),
        nn.LayerNorm(n_embd),
        init_linear(nn.Linear(n_embd, out)),
    )


class Decentralised(PolicyNetwork):
    """Agents act independently from their own observations (MAT-Dec and MAPPO)."""

    def actor(self, obs: Tensor) -> Tensor:
        raise NotImplementedError

    def action_params(self, obs: Tensor, actions: Tensor) -> tuple[Tensor, Tensor]:
        return self.actor(obs), self.values(obs)

    @torch.no_grad()
    def act(self, obs, available=None, deterministic=False, generator=None):
        dist = self.dist.make(self.actor(obs), self.std(), available)
        actions = self.dist.sample(dist, deterministic, generator)
        return actions, self.dist.log_prob_entropy(dist, actions)[0], self.values(obs)


class MATDec(Decentralised):
    """MAT's encoder as the critic; one shared MLP actor per agent."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        self.encoder = Encoder(cfg)
        self.mlp = actor_mlp(cfg.obs_dim, cfg.n_embd, cfg.action_size)

    def actor(self, obs: Tensor) -> Tensor:
        return self.mlp(obs)

    def values(self, obs: Tensor) -> Tensor:
        return self.encoder(obs)[1]


def centralised_critic(cfg: ModelConfig) -> nn.Sequential:
    """MAPPO's critic: an MLP on the joint observation plus the agent's own."""
    return actor_mlp(cfg.obs_dim * (cfg.n_agents + 1), cfg.n_embd, 1)


def centralised_values(critic: nn.Module, obs: Tensor, cfg: ModelConfig) -> Tensor:
    """Each agent's value [B, n, 1] from `centralised_critic`, for exactly `cfg.n_agents`."""
    batch, n, _ = obs.shape
    if n != cfg.n_agents:
        raise ValueError(
            f"this {cfg.algo.upper()} critic was built for {cfg.n_agents} agents, got {n}"
        )
    joint = obs.reshape(batch, 1, -1).expand(batch, n, -1)
    return critic(torch.cat((joint, obs), dim=-1))


class MAPPO(Decentralised):
    """Shared MLP actor; centralised critic on the joint observation plus the agent's own."""

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        self.mlp = actor_mlp(cfg.obs_dim, cfg.n_embd, cfg.action_size)
        self.critic = centralised_critic(cfg)

    def actor(self, obs: Tensor) -> Tensor:
        return self.mlp(obs)

    def values(self, obs: Tensor) -> Tensor:
        return centralised_values(self.critic, obs, self.cfg)


class AgentActor(nn.Module):
    """One HAPPO agent's own actor: the MLP and (continuous) its action std."""

    def __init__(self, cfg: ModelConfig):
        super().__init__()
        self.mlp = actor_mlp(cfg.obs_dim, cfg.n_embd, cfg.action_size)
        if cfg.action_type == "continuous":
            self.log_std = nn.Parameter(torch.ones(cfg.action_size))


class HAPPO(Decentralised):
    """HAPPO (Kuba et al., ICLR 2022; HARL): MAPPO's centralised critic, and a separate actor
    per agent, which the update trains one after another (`mat_sdk.training.happo`)."""

    shared_std = False

    def __init__(self, cfg: ModelConfig):
        super().__init__(cfg)
        self.actors = nn.ModuleList(AgentActor(cfg) for _ in range(cfg.n_agents))
        self.critic = centralised_critic(cfg)

    def std(self) -> Tensor | None:
        """[n, A]: each agent's own, parametrised as the shared one (`PolicyNetwork.std`)."""
        if self.cfg.action_type != "continuous":
            return None
        return official_std(torch.stack([a.log_std for a in self.actors]))

    def actor(self, obs: Tensor) -> Tensor:
        if obs.shape[1] != self.cfg.n_agents:
            raise ValueError(
                f"this HAPPO policy has actors for {self.cfg.n_agents} agents, got {obs.shape[1]}"
            )
        return torch.stack([a.mlp(obs[:, i]) for i, a in enumerate(self.actors)], dim=1)

    def values(self, obs: Tensor) -> Tensor:
        return centralised_values(self.critic, obs, self.cfg)

    def agent_log_prob(
        self, agent: int, obs: Tensor, actions: Tensor, available: Tensor | None = None
    ) -> tuple[Tensor, Tensor]:
        """Agent `agent`'s log-probs and entropies [B, A or 1] of its taken actions, from
        its own actor alone (the others' graphs are not built)."""
        actor = self.actors[agent]
        std = official_std(actor.log_std) if self.cfg.action_type == "continuous" else None
        mask = None if available is None else available[:, agent]
        dist = self.dist.make(actor.mlp(obs[:, agent]), std, mask)
        return self.dist.log_prob_entropy(dist, actions[:, agent])


POLICIES: dict[str, type[PolicyNetwork]] = {
    "mat": MAT,
    "mat-dec": MATDec,
    "mappo": MAPPO,
    "happo": HAPPO,
}


def build_policy(cfg: ModelConfig) -> PolicyNetwork:
    """The untrained policy network of `cfg.algo` (`mat_sdk.policy.algorithms`)."""
    return POLICIES[cfg.algo](cfg)


def check_fits(cfg: ModelConfig, env, env_id: str) -> None:
    """Refuse an env (a team or vectorised envs) that a policy of `cfg` cannot act on, saying
    why: its observation size, its action type and size, and for MAPPO, whose centralised
    critic reads every agent at once, its agent count. The one fit check: training on several
    envs, evaluating, fine-tuning and exporting all ask it."""
    if env.obs_dim != cfg.obs_dim:
        raise ValueError(
            f"{env_id} gives observations of size {env.obs_dim}, but the policy takes size "
            f"{cfg.obs_dim}; the robots differ (or one-hot agent ids are on in one and off in "
            "the other; ids of one family share a size: `mat envs` marks families)"
        )
    if env.action_type != cfg.action_type or env.action_size != cfg.action_size:
        raise ValueError(
            f"{env_id} has {env.action_type} actions of size {env.action_size}, the policy "
            f"{cfg.action_type} of size {cfg.action_size}"
        )
    if cfg.fixed_team and env.n_agents != cfg.n_agents:
        raise ValueError(
            f"{cfg.algo.upper()}'s centralised critic is tied to {cfg.n_agents} agents; "
            f"{env_id} has {env.n_agents}"
        )
