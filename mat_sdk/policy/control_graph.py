"""`decode.onnx`: the whole control step in one ONNX Runtime call, built from the weights.

    obs [B, n, obs_dim], noise [B, n, A] (, available [B, n, A]) ->
    actions (, clipped_actions), mean + std (continuous) or logits (discrete), values,
    obs_check

Why a hand-built graph: at B = 1 a control step is bound by kernel dispatch, not arithmetic,
and the torch-exported step graph ran several times more kernels per agent than this one.
Written directly in ONNX it is laid out for that regime: an agent's activations are [B, 1, C],
the layout in which ONNX Runtime fuses bias + residual + LayerNorm and bias + GELU at load;
q/k/v projections are fused; with one head (the paper's size) attention scores the cached
action stream itself (the query pulled through the key projection, the value projection folded
into the output one — see `_stream_queries`), with several it caches per-head keys and values
(`_streamed`); ONNX's `Attention` op (opset 24) either way; everything that does not depend on
the actions already chosen (the second attention's queries, noise times std, the mask) is
computed for all agents before the agent steps, and the agents' action means after them.
About 20 kernels per agent remain. With an `attention_window` W the encoder attends over
gathered neighbours (`_banded_attention`) and each agent step keeps the last W cache entries,
so the step costs O(n W). The steps run in ONNX `Loop`s (any agent count) or are
written out for one count (`agents=N`: `decode_nN.onnx`, no loop machinery). Only standard
ONNX ops. BENCHMARKS.md has the measurements.

The exporter (`mat_export`) writes it into bundles and ONNX rollouts (`mat_sdk.training.onnx_actor`)
act through it; both sit above this module, so it lives beside the model it is built from.
The exporter checks this graph against the torch policy on several agent counts and refuses
the bundle when they differ, so it cannot drift from `mat_sdk.policy.model`.
"""

from __future__ import annotations

import numpy as np
import onnx
import torch
from onnx import TensorProto, helper, numpy_helper

from mat_sdk.policy.model import MAT, UNAVAILABLE_LOGIT, PolicyNetwork

OPSET = 24  # `Attention` with a KV cache
BODY = 8  # agent steps per iteration of the any-count graph's second `Loop`
FLOAT, INT64 = TensorProto.FLOAT, TensorProto.INT64
LN_EPS = 1e-5  # torch.nn.LayerNorm's default


def _streamed(cfg) -> bool:
    """Whether the decoder's attention scores the cached action stream itself (one head) or
    per-head keys and values (several heads). Streaming saves the key/value projections but
    gives every head the stream's full width, which loses to per-head caches as heads grow
    (BENCHMARKS.md)."""
    return cfg.n_head == 1


def _cache_dims(cfg) -> list[int]:
    """One agent's cache entry: [width] of its action stream entry (`_streamed`), else
    [heads, head width] of its keys or values."""
    return [cfg.n_embd] if _streamed(cfg) else [cfg.n_head, cfg.n_embd // cfg.n_head]


def _cache_kinds(cfg) -> tuple[str, ...]:
    """The caches of one decoder attention: the stream itself, or its keys and values."""
    return ("stream",) if _streamed(cfg) else ("key", "value")


class GraphBuilder:
    """Collects nodes and initializers; every helper returns the name of its output."""

    def __init__(self, weights: dict[str, np.ndarray], prefix: str = ""):
        self.weights, self.prefix = weights, prefix
        self.nodes: list[onnx.NodeProto] = []
        self.initializers: list[onnx.TensorProto] = []
        self.constants: dict[tuple, str] = {}  # one initializer per distinct value
        self._count = 0

    def _name(self, hint: str) -> str:
        self._count += 1
        return f"{self.prefix}{hint}_{self._count}"

    def const(self, value, hint: str = "const", dtype=np.float32) -> str:
        array = np.asarray(value, dtype=dtype)
        key = (hint, array.dtype.str, array.shape, array.tobytes())
        if key not in self.constants:
            self.constants[key] = name = self._name(hint)
            self.initializers.append(numpy_helper.from_array(array, name))
        return self.constants[key]

    def op(self, op_type: str, *inputs: str, outputs: int | list[str] = 1, **attrs):
        names = (
            [self._name(op_type.lower()) for _ in range(outputs)]
            if isinstance(outputs, int)
            else outputs
        )
        self.nodes.append(helper.make_node(op_type, list(inputs), names, **attrs))
        return names[0] if len(names) == 1 else names

    # ---- layers, named after the state-dict prefixes of mat_sdk.policy.model
    def linear(self, x: str, layer: str, scale=1.0, shift=0.0) -> str:
        """y = x W^T + b (times `scale` plus `shift`, folded into the weights)."""
        weight = self.weights[f"{layer}.weight"].T * scale
        bias = self.weights.get(f"{layer}.bias", np.zeros(weight.shape[1], np.float32))
        return self.dense(x, weight, bias * scale + shift, layer)

    def dense(self, x: str, weight, bias, hint: str) -> str:
        """x @ weight + bias; a `str` bias names a tensor (e.g. a per-agent one) to add."""
        b = bias if isinstance(bias, str) else self.const(bias, hint + ".b")
        return self.op("Add", self.op("MatMul", x, self.const(weight, hint + ".w")), b)

    def layer_norm(self, x: str, layer: str) -> str:
        scale = self.const(self.weights[f"{layer}.weight"], layer + ".scale")
        bias = self.const(self.weights[f"{layer}.bias"], layer + ".bias")
        return self.op("LayerNormalization", x, scale, bias, axis=-1, epsilon=LN_EPS)

    def gelu(self, x: str) -> str:
        return self.op("Gelu", x)

    def qkv(self, x: str, attn: str, parts: tuple[str, ...]) -> list[str]:
        """The projections in `parts` as one matrix product, split into [B, L, C] tensors."""
        weight = np.concatenate([self.weights[f"{attn}.{p}.weight"].T for p in parts], axis=1)
        bias = np.concatenate([self.weights[f"{attn}.{p}.bias"] for p in parts])
        fused = self.dense(x, weight, bias, f"{attn}.{''.join(p[0] for p in parts)}")
        return self.op("Split", fused, outputs=len(parts), axis=-1, num_outputs=len(parts))


def _weights(policy: PolicyNetwork) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in policy.state_dict().items()}


def _value(name: str, shape) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, FLOAT, shape)


def build_decode(
    policy: PolicyNetwork,
    obs_mean: np.ndarray,
    obs_scale: np.ndarray,
    obs_clip,
    value_mean,
    value_std,
    agents: int | None = None,
    action_bounds: tuple[float, float] = (-1.0, 1.0),
) -> onnx.ModelProto:
    """The control-step graph for a MAT, MAT-Dec or MAPPO policy with its normalisers; for
    any agent count, or specialised (unrolled, for MAT) to exactly `agents`.

    Besides the actions (as sampled: what the next agent is conditioned on) it returns what
    the runtime would otherwise compute with numpy around the call, where each ufunc costs
    more than a kernel does here (BENCHMARKS.md):
    `clipped_actions` (continuous; clipped to `action_bounds`) and `obs_check`, the sum of
    all observations, finite unless one is NaN or inf (or the sum overflows, which the
    runtime double-checks).
    """
    cfg = policy.cfg
    discrete = cfg.action_type == "discrete"
    g = GraphBuilder(_weights(policy))
    n = agents or "agents"
    inputs = [
        _value("obs", ["batch", n, cfg.obs_dim]),
        _value("noise", ["batch", n, cfg.action_size]),
    ]
    if discrete:
        inputs.append(_value("available", ["batch", n, cfg.action_size]))
    x = g.op("Mul", g.op("Sub", "obs", g.const(obs_mean)), g.const(obs_scale))
    if obs_clip is not None:
        x = g.op("Clip", x, g.const(-obs_clip), g.const(obs_clip))
    value_fold = {"scale": value_std, "shift": value_mean}  # ValueNorm's de-normalisation
    std = None if discrete else policy.std().detach().cpu().numpy()
    shift = _noise_shift(g, std)
    algorithm = cfg.algorithm
    if algorithm.autoregressive:
        rep, values = _encoder(g, x, cfg, value_fold)
        tokens = _normalised_tokens(policy)
        first = _first_attentions(policy, tokens[0])
        params = _decoder(g, rep, cfg, shift, agents, tokens, first)
    else:
        if algorithm.centralised_critic:
            values = _mappo_values(g, x, cfg, value_fold)
        else:
            values = _encoder(g, x, cfg, value_fold)[1]
        actor = _agent_actors(g, x, cfg) if algorithm.actor_per_agent else _mlp(g, x, "mlp")
        params = _decentralised_sample(g, actor, shift, discrete)
    head = ["logits"] if discrete else ["mean", "std"]
    g.op("Identity", values, outputs=["values"])
    if not discrete:
        g.op("Expand", g.const(std, "std"), g.op("Shape", params["mean"]), outputs=["std"])
        low, high = (g.const(bound, "bound") for bound in action_bounds)
        g.op("Clip", params["actions"], low, high, outputs=["clipped_actions"])
    for name in ["actions", *(h for h in head if h != "std")]:
        g.op("Identity", params[name], outputs=[name])
    g.op("ReduceSum", "obs", keepdims=0, outputs=["obs_check"])
    clipped = {} if discrete else {"clipped_actions": cfg.action_size}
    widths = {
        "actions": 1 if discrete else cfg.action_size,
        **clipped,
        **dict.fromkeys(head, cfg.action_size),
        "values": 1,
    }
    outputs = [_value(name, ["batch", n, w]) for name, w in widths.items()]
    outputs.append(_value("obs_check", []))
    graph = helper.make_graph(g.nodes, "mat_decode", inputs, outputs, g.initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 10
    return model


def _encoder(g: GraphBuilder, x: str, cfg, value_fold: dict) -> tuple[str, str]:
    """mat_sdk.policy.model.Encoder: rep [B, n, C] and de-normalised values [B, n, 1]."""
    x = g.gelu(g.linear(g.layer_norm(x, "encoder.obs_encoder.0"), "encoder.obs_encoder.1"))
    x = g.layer_norm(x, "encoder.ln")
    band = None if cfg.attention_window is None else _band(g, x, cfg.attention_window)
    for b in range(cfg.n_block):
        block = f"encoder.blocks.{b}"
        q, k, v = g.qkv(x, f"{block}.attn", ("query", "key", "value"))
        if band is None:
            attended = g.op("Attention", q, k, v, q_num_heads=cfg.n_head, kv_num_heads=cfg.n_head)
        else:
            attended = _banded_attention(g, q, k, v, cfg, *band)
        x = g.layer_norm(g.op("Add", x, g.linear(attended, f"{block}.attn.proj")), f"{block}.ln1")
        x = g.layer_norm(g.op("Add", x, _mlp_block(g, x, f"{block}.mlp")), f"{block}.ln2")
    return x, _head(g, x, "encoder.head", **value_fold)


def _band(g: GraphBuilder, x: str, window: int) -> tuple[str, str]:
    """Each agent's 2 window - 1 neighbours in `x` [B, n, C], for every encoder block: their
    indices [n, span] (clamped into the team) and a score mask [n, 1, 1, span], -inf for
    those past either end."""
    count = g.op("Squeeze", g.op("Shape", x, start=1, end=2))
    agents = g.op("Range", g.const(0, "zero_i", np.int64), count, g.const(1, "one_i", np.int64))
    offsets = g.const(np.arange(-(window - 1), window), "offsets", np.int64)
    neighbours = g.op("Add", g.op("Unsqueeze", agents, g.const([1], "axis1", np.int64)), offsets)
    inside = g.op(
        "And",
        g.op("GreaterOrEqual", neighbours, g.const(0, "zero_i", np.int64)),
        g.op("Less", neighbours, count),
    )  # [n, span]
    index = g.op("Where", inside, neighbours, g.const(0, "zero_i", np.int64))
    outside = g.op("Where", inside, g.const(0.0, "zero"), g.const(-np.inf, "minus_inf"))
    return index, g.op("Unsqueeze", outside, g.const([1, 2], "axes12", np.int64))


def _banded_attention(g: GraphBuilder, q: str, k: str, v: str, cfg, index, outside) -> str:
    """Attention of every agent over the agents fewer than W = `cfg.attention_window` places
    away, on [B, n, C] tensors, in O(n W) time and memory: each agent's 2 W - 1 neighbours'
    keys and values are gathered ([B, n, 2 W - 1, C]; `_band`'s `index` and `outside`), so
    no [n, n] score matrix is ever formed."""
    heads, span = cfg.n_head, 2 * cfg.attention_window - 1
    split = g.const([0, 0, span, heads, -1], "split", np.int64)  # [B, n, span, H, d]
    keys = g.op("Reshape", g.op("Gather", k, index, axis=1), split)
    values = g.op("Reshape", g.op("Gather", v, index, axis=1), split)
    query = g.op("Reshape", q, g.const([0, 0, heads, 1, -1], "query", np.int64))  # [B, n, H, 1, d]
    scores = g.op("MatMul", query, g.op("Transpose", keys, perm=[0, 1, 3, 4, 2]))
    scale = g.const(1 / np.sqrt(cfg.n_embd // heads), "scale")
    scores = g.op("Add", g.op("Mul", scores, scale), outside)  # [B, n, H, 1, span]
    weights = g.op("Softmax", scores, axis=-1)
    mixed = g.op("MatMul", weights, g.op("Transpose", values, perm=[0, 1, 3, 2, 4]))
    return g.op("Reshape", mixed, g.const([0, 0, -1], "merge", np.int64))  # [B, n, C]


def _mlp_block(g: GraphBuilder, x: str, prefix: str) -> str:
    return g.linear(g.gelu(g.linear(x, f"{prefix}.0")), f"{prefix}.2")


def _head(g: GraphBuilder, x: str, prefix: str, scale=1.0, shift=0.0) -> str:
    x = g.layer_norm(g.gelu(g.linear(x, f"{prefix}.0")), f"{prefix}.2")
    return g.linear(x, f"{prefix}.3", scale, shift)


def _mlp(g: GraphBuilder, x: str, prefix: str, **value_fold) -> str:
    """mat_sdk.policy.model.actor_mlp: LN, Linear, GELU, LN, Linear, GELU, LN, Linear."""
    x = g.gelu(g.linear(g.layer_norm(x, f"{prefix}.0"), f"{prefix}.1"))
    x = g.gelu(g.linear(g.layer_norm(x, f"{prefix}.3"), f"{prefix}.4"))
    return g.linear(g.layer_norm(x, f"{prefix}.6"), f"{prefix}.7", **value_fold)


def _agent_actors(g: GraphBuilder, x: str, cfg) -> str:
    """HAPPO: agent i's own MLP (`actors.i.mlp`) on its observation, side by side [B, n, A]."""
    outputs = []
    for i in range(cfg.n_agents):
        start, end = g.const([i], "agent", np.int64), g.const([i + 1], "agent", np.int64)
        mine = g.op("Slice", x, start, end, g.const([1], "axis", np.int64))
        outputs.append(_mlp(g, mine, f"actors.{i}.mlp"))
    return g.op("Concat", *outputs, axis=1)


def _mappo_values(g: GraphBuilder, x: str, cfg, value_fold: dict) -> str:
    """The centralised critic: every agent's input is the joint observation plus its own."""
    joint = g.op("Reshape", x, g.const([0, 1, cfg.n_agents * cfg.obs_dim], "joint", np.int64))
    shape = g.op("Concat", g.op("Shape", x, end=2), g.const([-1], "last", np.int64), axis=0)
    per_agent = g.op("Expand", joint, g.op("Max", shape, g.const([1], "one", np.int64)))
    return _mlp(g, g.op("Concat", per_agent, x, axis=-1), "critic", **value_fold)


def _mask(g: GraphBuilder, logits: str) -> str:
    """Unavailable choices get UNAVAILABLE_LOGIT, exactly as the torch policy's masked_fill."""
    unavailable = g.op("Equal", "available", g.const(0.0, "zero"))
    return g.op("Where", unavailable, g.const(UNAVAILABLE_LOGIT, "masked"), logits)


def _noise_shift(g: GraphBuilder, std: np.ndarray | None) -> str:
    """What sampling adds to the action parameters, for all agents at once [B, n, A]:
    continuous `std * noise` (actions = mean + it); discrete the mask plus the Gumbel noise
    (choice = argmax(logits + it)). Zero noise leaves the deterministic action."""
    if std is None:
        return g.op("Add", _mask(g, g.const(0.0, "zero")), "noise")
    return g.op("Mul", "noise", g.const(std, "std"))


def _decentralised_sample(g: GraphBuilder, params: str, shift: str, discrete: bool):
    if discrete:
        index = g.op("ArgMax", g.op("Add", params, shift), axis=-1, keepdims=1)
        return {"actions": g.op("Cast", index, to=FLOAT), "logits": _mask(g, params)}
    return {"actions": g.op("Add", params, shift), "mean": params}


def _decoder(
    g: GraphBuilder, rep: str, cfg, shift: str, agents: int | None, tokens, first_attentions
):
    """`model.Decoder` run agent by agent with caches: an ONNX `Loop` over any number of
    agents, or (`agents` given) the steps written out one after another for that count.

    The steps are cut to the kernels that depend on the actions already chosen (each is a
    dispatch at B = 1): per-agent tensors stay [B, 1, C], the layout ONNX Runtime fuses bias,
    residual and LayerNorm in (`SkipLayerNormalization`, `BiasGelu`) and `Attention` takes
    without reshapes; the next agent's normalised token comes straight from this agent's
    head (continuous: head, sampling shift and action encoder as one matrix; discrete: a
    lookup in pre-normalised token rows), and the action means are computed for all agents
    afterwards.
    """
    discrete = cfg.action_type == "discrete"
    w = g.weights
    # ---- before the agent steps, for all agents at once: [B, n, ...] tensors they slice
    per_agent, widths = {"rep": rep}, {"rep": cfg.n_embd}
    for b in range(cfg.n_block):  # the second attention's queries come from rep alone
        weight, bias = _queries(w, cfg, f"decoder.blocks.{b}.attn2")
        per_agent[f"query2.{b}"] = g.dense(rep, weight, bias, f"query2.{b}")
        widths[f"query2.{b}"] = weight.shape[1]
    embed = w["decoder.action_encoder.0.weight"].T  # [token, C]
    if discrete:
        per_agent["shift"], widths["shift"] = shift, cfg.action_size
    else:  # what the next agent's token adds to hidden @ (head.3 -> action encoder)
        token_bias = w["decoder.head.3.bias"] @ embed + w["decoder.action_encoder.0.bias"]
        per_agent["token"] = g.dense(shift, embed, token_bias, "token")
        widths["token"] = cfg.n_embd
    batch = g.op("Shape", rep, end=1)
    row = g.op("Concat", batch, g.const([1, cfg.n_embd], "row", np.int64), axis=0)
    first = g.op("Expand", g.const(tokens[:1][None], "first"), row)  # agent 0's: the start
    caches = [
        f"{b}.{attn}.{kind}"
        for b in range(cfg.n_block)
        for attn in ("attn1", "attn2")
        for kind in _cache_kinds(cfg)
    ]
    step = _AgentStep(cfg, discrete, embed, tokens[1:], first_attentions)
    if agents is None:
        empty = [_empty_cache(g, cfg, batch)] * len(caches)
        outputs = _loop(g, step, per_agent, widths, batch, first, empty, caches)
    else:  # the first agent's attentions see only its own entry: streamed, no cache needed
        empty = None if _streamed(cfg) else [_empty_cache(g, cfg, batch)] * len(caches)
        outputs = _unrolled(g, step, per_agent, first, empty, agents)
    if discrete:
        actions = g.op(
            "Unsqueeze", g.op("Cast", outputs["chosen"], to=FLOAT), g.const([2], "axis2", np.int64)
        )
        return {"actions": actions, "logits": _mask(g, outputs["logits"])}
    mean = g.linear(outputs["hidden"], "decoder.head.3")
    return {"actions": g.op("Add", mean, shift), "mean": mean}


def _empty_cache(g: GraphBuilder, cfg, batch: str) -> str:
    """A cache holding no agents yet: [B, 0, C] (stream) or [B, heads, 0, head width]."""
    dims = _cache_dims(cfg)
    no_agents = g.op("Concat", batch, g.const([*dims[:-1], 0, dims[-1]], "cache", np.int64), axis=0)
    zero = numpy_helper.from_array(np.zeros(1, np.float32))
    return g.op("ConstantOfShape", no_agents, value=zero)


def _normalised_tokens(policy: MAT) -> np.ndarray:
    """What the decoder makes of its action tokens, LayerNorm(action encoder(token)), computed
    by the model itself: row 0 the start token, then (discrete) every choice's one-hot."""
    decoder = policy.decoder
    device = decoder.ln.weight.device
    if policy.cfg.action_type == "discrete":
        onehots = torch.eye(decoder.token_dim, device=device)
    else:  # only the start token (zeros); later tokens depend on the continuous action
        onehots = torch.zeros(1, decoder.token_dim, device=device)
    with torch.no_grad():
        return decoder.ln(decoder.action_encoder(onehots)).cpu().numpy().astype(np.float32)


class _AgentStep:
    """One agent's decoder step on [B, 1, C] activations; writes its nodes into a builder."""

    def __init__(self, cfg, discrete: bool, embed: np.ndarray, choices: np.ndarray, first):
        """`embed`: the action encoder's matrix; `choices`: each discrete choice's
        normalised token (unused for continuous actions); `first`: `_first_attentions`."""
        self.cfg, self.discrete, self.embed, self.choices = cfg, discrete, embed, choices
        self.first_attentions = first

    def outputs(self) -> dict[str, int]:
        """What every step emits for the whole team: name -> width (0: one choice per row)."""
        if self.discrete:
            return {"chosen": 0, "logits": self.cfg.action_size}
        return {"hidden": self.cfg.n_embd}

    def __call__(
        self, g: GraphBuilder, mine: dict, x: str, past: list[str] | None, last: bool = False
    ):
        """`mine`: this agent's [B, 1, ..] slices of the per-agent tensors; `x`: its normalised
        token; `past`: the caches of the agents before it, None for the team's first agent
        (streamed attention only). -> (the next agent's token, None when `last`; present
        caches; `outputs()`)."""
        cfg, w = self.cfg, g.weights
        present: list[str] = []
        kinds = len(_cache_kinds(cfg))  # caches per attention
        for b in range(cfg.n_block):
            block, past1, past2 = f"decoder.blocks.{b}", None, None
            if past is None and b == 0:  # the first agent's first attentions: constants
                stream2, attended = self.first_attentions
                present += [x, g.op("Expand", g.const(stream2, "stream2"), g.op("Shape", x))]
                x = g.layer_norm(g.op("Add", mine["rep"], g.const(attended)), f"{block}.ln2")
            else:
                if past is not None:
                    cache = past[2 * kinds * b : 2 * kinds * (b + 1)]
                    past1, past2 = cache[:kinds], cache[kinds:]
                attended = _attention(g, cfg, x, f"{block}.attn1", past1, present)
                x = g.layer_norm(g.op("Add", x, attended), f"{block}.ln1")
                query = mine[f"query2.{b}"]
                attended = _attention(g, cfg, x, f"{block}.attn2", past2, present, query)
                x = g.layer_norm(g.op("Add", mine["rep"], attended), f"{block}.ln2")
            x = g.layer_norm(g.op("Add", x, _mlp_block(g, x, f"{block}.mlp")), f"{block}.ln3")
        hidden = g.layer_norm(g.gelu(g.linear(x, "decoder.head.0")), "decoder.head.2")
        if not self.discrete:  # next token from (hidden @ head.3 + shift) @ action encoder
            if last:
                return None, present, {"hidden": hidden}
            weight = w["decoder.head.3.weight"].T @ self.embed
            token = g.dense(hidden, weight, mine["token"], "next_token")
            return g.layer_norm(g.gelu(token), "decoder.ln"), present, {"hidden": hidden}
        logits = g.linear(hidden, "decoder.head.3")
        chosen = g.op("ArgMax", g.op("Add", logits, mine["shift"]), axis=-1, keepdims=0)
        tokens = g.const(self.choices, "tokens")
        token = None if last else g.op("Gather", tokens, chosen, axis=0)
        return token, present, {"chosen": chosen, "logits": logits}


def _loop(
    g: GraphBuilder, step: _AgentStep, per_agent: dict, widths, batch: str, first, empty, caches
):
    """The agent steps for any agent count n in two ONNX `Loop`s: b single steps, then a
    bodies of `BODY` steps written out (fewer loop iterations; bodies of 16 or tiers of 1, 4,
    16 measured no better, BENCHMARKS.md), with n = BODY a + b and 1 <= b <= BODY. The single
    steps so run at least once, and the bodies' loop (zero times for n <= BODY) sits in an
    `If` that skips it then: OpenVINO's CPU plugin refuses a `Loop` that runs zero times (it
    bounds the carried caches below by one iteration's growth), and computes one inside an
    `If` wrong when the single steps' loop is guarded too. -> [B, n, ..] outputs."""
    packed = g.op("Concat", *per_agent.values(), axis=-1)
    agents = g.op("Shape", "obs", start=1, end=2)
    one, body = g.const([1], "one", np.int64), g.const([BODY], "body", np.int64)
    singles = g.op("Add", g.op("Mod", g.op("Sub", agents, one), body), one)
    bodies = g.op("Div", g.op("Sub", agents, singles), body)
    # what the steps so far output, [B, agents so far, ..]: nothing yet
    outputs = {name: _none_yet(g, batch, size) for name, size in step.outputs().items()}
    carried = [first, *empty]
    for count, trips, start, guarded in ((1, singles, None, False), (BODY, bodies, singles, True)):
        steps = g.const(np.arange(count), "steps", np.int64)
        first_agents = steps if start is None else g.op("Add", start, steps)
        carried, outputs = _loop_run(
            g, step, packed, widths, carried, outputs, caches, count, trips, first_agents, guarded
        )
    return outputs


def _none_yet(g: GraphBuilder, batch: str, size: int) -> str:
    """No agent's output yet: [B, 0, size] floats, or [B, 0] integers (`size` 0: choices)."""
    rest = [0, size] if size else [0]
    dtype = np.float32 if size else np.int64
    shape = g.op("Concat", batch, g.const(rest, "rest", np.int64), axis=0)
    return g.op("Expand", g.const(np.zeros([1, *rest]), "none", dtype), shape)


def _loop_run(
    g: GraphBuilder,
    step,
    packed,
    widths,
    carried,
    outputs,
    caches,
    count,
    trips,
    first_agents,
    guarded,
):
    """One `Loop` whose body runs `count` agent steps; iteration i serves the agents
    `first_agents + i * count` and appends their outputs to `outputs` [B, agents so far, ..],
    carried through the loop: no scan outputs, whose stacking engines disagree on (ONNX's
    reference evaluator concatenates them on their first axis, ONNX Runtime stacks them on
    a new one) and which a loop that runs zero times leaves without a shape. `guarded`: the
    `Loop` sits in an `If` that passes the carried values on unchanged when `trips` is 0.
    -> (final carried values, {name: [B, agents so far, ..]})."""
    body = GraphBuilder(g.weights, prefix=f"steps{count}/")
    i, cond, x = (f"steps{count}/{name}" for name in ("i", "cond", "x"))
    past = [f"steps{count}/past.{c}" for c in caches]
    done = {name: f"steps{count}/done.{name}" for name in outputs}
    index = body.op("Add", body.op("Mul", i, body.const(count, "count", np.int64)), first_agents)
    mine = body.op("Gather", packed, index, axis=1)  # [B, count, all per-agent widths]
    sizes = body.const(list(widths.values()), "sizes", np.int64)
    parts = body.op("Split", mine, sizes, axis=-1, outputs=len(widths))
    slices = {name: _split(body, part, count) for name, part in zip(widths, parts, strict=True)}
    token, present, new = _steps(body, step, slices, x, past, count)
    grown = {name: body.op("Concat", done[name], new[name], axis=1) for name in outputs}
    width = step.cfg.n_embd
    dims = _cache_dims(step.cfg)
    cache_shape = ["batch", *dims[:-1], "past", dims[-1]]

    def accumulated(name: str, tensor: str, agents: str) -> onnx.ValueInfoProto:
        size = step.outputs()[name]
        if size == 0:
            return helper.make_tensor_value_info(tensor, INT64, ["batch", agents])
        return _value(tensor, ["batch", agents, size])

    loop_body = helper.make_graph(
        body.nodes,
        f"steps{count}",
        [
            helper.make_tensor_value_info(i, INT64, []),
            helper.make_tensor_value_info(cond, TensorProto.BOOL, []),
            _value(x, ["batch", 1, width]),
            *(_value(p, cache_shape) for p in past),
            *(accumulated(name, done[name], "agents_before") for name in outputs),
        ],
        [
            # cond passed on under a name of its own, as every carried value has
            helper.make_tensor_value_info(body.op("Identity", cond), TensorProto.BOOL, []),
            _value(token, ["batch", 1, width]),
            *(_value(p, cache_shape) for p in present),
            *(accumulated(name, grown[name], "agents_after") for name in outputs),
        ],
        body.initializers,
    )
    state = [*carried, *outputs.values()]
    trip_count = g.op("Squeeze", trips)
    ran = GraphBuilder(g.weights, prefix=f"run{count}/") if guarded else g
    # a name per carried value: OpenVINO's ONNX reader counts a tensor given twice once (the
    # empty caches); ONNX Runtime drops these Identities at load
    distinct = [ran.op("Identity", name) for name in state]
    looped = ran.op(
        "Loop", trip_count, g.const(True, "true", np.bool_), *distinct, outputs=len(state),
        body=loop_body,
    )  # fmt: skip
    if guarded:
        types = [FLOAT] * len(carried) + [FLOAT if s else INT64 for s in step.outputs().values()]
        skipped = GraphBuilder(g.weights, prefix=f"skip{count}/")
        unchanged = [skipped.op("Identity", name) for name in state]
        looped = g.op(
            "If", g.op("Greater", trip_count, g.const(0, "zero", np.int64)), outputs=len(state),
            then_branch=_branch(ran, f"run{count}", looped, types),
            else_branch=_branch(skipped, f"skip{count}", unchanged, types),
        )  # fmt: skip
    return looped[: len(carried)], dict(zip(outputs, looped[len(carried) :], strict=True))


def _branch(g: GraphBuilder, name: str, outputs: list[str], types: list[int]) -> onnx.GraphProto:
    """An `If` branch: `g`'s nodes, reading the enclosing graph's values, giving `outputs`."""
    values = [
        helper.make_tensor_value_info(o, t, None) for o, t in zip(outputs, types, strict=True)
    ]
    return helper.make_graph(g.nodes, name, [], values, g.initializers)


def _split(g: GraphBuilder, tensor: str, count: int) -> list[str]:
    """[B, count, ..] -> `count` tensors [B, 1, ..], one per agent."""
    return (
        [tensor] if count == 1 else g.op("Split", tensor, axis=1, num_outputs=count, outputs=count)
    )


def _steps(g: GraphBuilder, step: _AgentStep, slices: dict, x: str, past, count: int, end=False):
    """`count` consecutive agent steps; `slices[name][j]` is the j-th agent's share. `end`: the
    last of them is the team's last agent. -> (next token, caches, {name: [B, count, ..]})."""
    collected = {name: [] for name in step.outputs()}
    for j in range(count):
        mine = {name: parts[j] for name, parts in slices.items()}
        x, past, outputs = step(g, mine, x, past, last=end and j == count - 1)
        for name, tensor in outputs.items():
            collected[name].append(tensor)
    concat = {
        n: ts[0] if count == 1 else g.op("Concat", *ts, axis=1) for n, ts in collected.items()
    }
    return x, past, concat


def _unrolled(g: GraphBuilder, step: _AgentStep, per_agent: dict, first: str, past, agents: int):
    """The agent steps written out for exactly `agents` agents: no loop machinery at all."""
    slices = {name: _split(g, tensor, agents) for name, tensor in per_agent.items()}
    return _steps(g, step, slices, first, past, agents, end=True)[2]


def _queries(w: dict, cfg, attn: str) -> tuple[np.ndarray, np.ndarray]:
    """The query projection of a decoder attention (stream queries when `_streamed`)."""
    if _streamed(cfg):
        return _stream_queries(w, attn, cfg.n_head)
    return w[f"{attn}.query.weight"].T, w[f"{attn}.query.bias"]


def _attention(g: GraphBuilder, cfg, stream, attn, past, present, query=None) -> str:
    """One agent's decoder attention over the agents so far, its own entry `stream` [B, 1, C]
    included: the output projection of the mixed values. `query`: [B, 1, ..] precomputed
    (the second attention's), else projected from `stream`. `past` None: no agents before
    (streamed only). Appends the caches to `present`; with an `attention_window`, only the
    last window - 1 agents of `past` are attended to, and kept."""
    heads = cfg.n_head
    if past is not None and cfg.attention_window is not None:
        keep = g.const([1 - cfg.attention_window], "keep", np.int64)
        end = g.const([np.iinfo(np.int64).max], "end", np.int64)
        axis = g.const([len(_cache_dims(cfg))], "cache_axis", np.int64)  # the agents' axis
        past = [g.op("Slice", p, keep, end, axis) for p in past]
    if _streamed(cfg):
        if past is None:  # the first agent: attending to its own entry alone returns it
            present.append(stream)
            return g.dense(stream, *_stream_output(g.weights, attn, heads), f"{attn}.out")
        if query is None:
            query = g.dense(stream, *_queries(g.weights, cfg, attn), f"{attn}.queries")
        return _stream_attention(g, query, stream, attn, past, heads, present)
    if query is None:
        query, key, value = g.qkv(stream, attn, ("query", "key", "value"))
    else:
        key, value = g.qkv(stream, attn, ("key", "value"))
    mixed, *caches = g.op(
        "Attention", query, key, value, "", *past, outputs=3, q_num_heads=heads, kv_num_heads=heads
    )
    present += caches
    return g.linear(mixed, f"{attn}.proj")


def _first_attentions(policy: MAT, start: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first agent's first block up to its second attention's output, computed by the
    model itself: that agent sees only its own entry, the start token, so all of it is fixed.
    -> (its entry in the second attention's stream [1, 1, C], that attention's output [C]),
    so the graph neither recomputes them per call nor loses the shapes ONNX Runtime fuses on.
    """
    block = policy.decoder.blocks[0]
    device = block.ln1.weight.device
    with torch.no_grad():
        x = torch.from_numpy(start).to(device)[None, None]
        stream2 = block.ln1(x + block.attn1(x, x)[0])
        attended = block.attn2(stream2, stream2)[0]  # one key: the query does not matter
    return stream2.cpu().numpy(), attended[0, 0].cpu().numpy()


def _stream_queries(w: dict, attn: str, heads: int) -> tuple[np.ndarray, np.ndarray]:
    """Per head, the query pulled through the key projection: x -> [H * C] "stream queries".

    score_j = q_h . (Wk_h s_j + bk_h) / sqrt(d) = (Wk_h^T q_h / sqrt(d)) . s_j + const(j-free),
    and softmax ignores the constant, so attention can score the raw action stream s_j.
    """
    wq, bq = w[f"{attn}.query.weight"].astype(np.float64), w[f"{attn}.query.bias"]
    wk = w[f"{attn}.key.weight"].astype(np.float64)
    d = wq.shape[0] // heads
    parts = [slice(h * d, (h + 1) * d) for h in range(heads)]
    weight = np.concatenate([wq[p].T @ wk[p] for p in parts], axis=1) / np.sqrt(d)
    bias = np.concatenate([bq[p] @ wk[p] for p in parts]) / np.sqrt(d)
    return weight.astype(np.float32), bias.astype(np.float32)


def _stream_output(w: dict, attn: str, heads: int) -> tuple[np.ndarray, np.ndarray]:
    """Value and output projections as one matrix on the heads' weighted streams [H * C]."""
    wv, bv = w[f"{attn}.value.weight"].astype(np.float64), w[f"{attn}.value.bias"]
    wp, bp = w[f"{attn}.proj.weight"].astype(np.float64), w[f"{attn}.proj.bias"]
    d = wv.shape[0] // heads
    parts = [slice(h * d, (h + 1) * d) for h in range(heads)]
    weight = np.concatenate([wv[p].T @ wp[:, p].T for p in parts], axis=0)
    return weight.astype(np.float32), (bv @ wp.T + bp).astype(np.float32)


def _stream_attention(g: GraphBuilder, queries, stream, attn, past: list[str], heads, present):
    """One agent's stream queries [B, 1, H*C] attend over the cached stream plus its own entry
    `stream` [B, 1, C]: ONNX `Attention` with H query heads sharing one key/value head of
    width C (the stream serves as both; scale already folded into the queries). The grown
    stream [B, agents so far, C] is the one cache, appended to `present`: one copy per step
    where `Attention`'s own past/present would keep (and copy) it twice, as keys and as values
    (measured faster at many agents, BENCHMARKS.md)."""
    full = g.op("Concat", past[0], stream, axis=1)
    mixed = g.op("Attention", queries, full, full, scale=1.0, q_num_heads=heads, kv_num_heads=1)
    present.append(full)
    weight, bias = _stream_output(g.weights, attn, heads)
    return g.dense(mixed, weight, bias, f"{attn}.out")
