"""`decode.onnx`: the whole control step in one ONNX Runtime call, built from the weights.

    obs [B, n, obs_dim], noise [B, n, A] (, available [B, n, A]) ->
    actions, mean + std (continuous) or logits (discrete), values

Why a hand-built graph: at B = 1 a control step is bound by kernel dispatch, not arithmetic
(~0.5-1 µs per ONNX Runtime kernel; the torch-exported step graph ran ~89 kernels per agent).
Written directly in ONNX it is laid out for that regime: each linear layer is one `Gemm` on
2-D per-agent tensors; q/k/v projections are fused; attention scores the cached action
stream itself (the query pulled through the key projection, the value projection folded into
the output one — see `_stream_queries`) with ONNX's `Attention` op (opset 24); everything
that does not depend on the actions already chosen (the second attention's queries, noise
times std, the availability mask) is computed for all agents before the agent steps, which
take their share with one `Gather`. The steps run in an ONNX `Loop` (any agent count) or are
written out for one count (`agents=N`: `decode_nN.onnx`, no loop machinery). Only standard
ONNX ops; ONNX Runtime fuses further at load. BENCHMARKS.md has the measurements.

The exporter checks this graph against the torch policy on several agent counts and refuses
the bundle when they differ, so it cannot drift from `mat_sdk.model`.
"""

from __future__ import annotations

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

from mat_sdk.model import MAPPO, MAT, UNAVAILABLE_LOGIT, Policy

OPSET = 24  # `Attention` with a KV cache
FLOAT, INT64 = TensorProto.FLOAT, TensorProto.INT64
LN_EPS = 1e-5  # torch.nn.LayerNorm's default


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

    # ---- layers, named after the state-dict prefixes of mat_sdk.model
    def linear(self, x: str, layer: str, two_d: bool = False, scale=1.0, shift=0.0) -> str:
        """y = x W^T + b (times `scale` plus `shift`, folded into the weights)."""
        weight = self.weights[f"{layer}.weight"].T * scale
        bias = self.weights.get(f"{layer}.bias", np.zeros(weight.shape[1], np.float32))
        return self.dense(x, weight, bias * scale + shift, two_d, layer)

    def dense(self, x: str, weight, bias, two_d: bool, hint: str) -> str:
        w, b = self.const(weight, hint + ".w"), self.const(bias, hint + ".b")
        if two_d:
            return self.op("Gemm", x, w, b)
        return self.op("Add", self.op("MatMul", x, w), b)

    def layer_norm(self, x: str, layer: str) -> str:
        scale = self.const(self.weights[f"{layer}.weight"], layer + ".scale")
        bias = self.const(self.weights[f"{layer}.bias"], layer + ".bias")
        return self.op("LayerNormalization", x, scale, bias, axis=-1, epsilon=LN_EPS)

    def gelu(self, x: str) -> str:
        return self.op("Gelu", x)

    def qkv(self, x: str, attn: str, parts: tuple[str, ...], two_d: bool) -> list[str]:
        """The projections in `parts` as one matrix product, split into [B, L, C] tensors."""
        weight = np.concatenate([self.weights[f"{attn}.{p}.weight"].T for p in parts], axis=1)
        bias = np.concatenate([self.weights[f"{attn}.{p}.bias"] for p in parts])
        fused = self.dense(x, weight, bias, two_d, f"{attn}.{''.join(p[0] for p in parts)}")
        if two_d:
            fused = self.op("Unsqueeze", fused, self.const([1], "axis1", np.int64))
        return self.op("Split", fused, outputs=len(parts), axis=-1, num_outputs=len(parts))


def _weights(policy: Policy) -> dict[str, np.ndarray]:
    return {k: v.detach().cpu().numpy().astype(np.float32) for k, v in policy.state_dict().items()}


def _value(name: str, shape) -> onnx.ValueInfoProto:
    return helper.make_tensor_value_info(name, FLOAT, shape)


def build_decode(
    policy: Policy,
    obs_mean: np.ndarray,
    obs_scale: np.ndarray,
    obs_clip,
    value_mean,
    value_std,
    agents: int | None = None,
) -> onnx.ModelProto:
    """The control-step graph for a MAT, MAT-Dec or MAPPO policy with its normalisers; for
    any agent count, or specialised (unrolled, for MAT) to exactly `agents`."""
    cfg = policy.cfg
    discrete = cfg.action_type == "discrete"
    g = GraphBuilder(_weights(policy))
    n = agents or "agents"
    inputs = [
        _value("obs", ["batch", n, cfg.obs_dim]),
        _value("noise", ["batch", n, cfg.action_dim]),
    ]
    if discrete:
        inputs.append(_value("available", ["batch", n, cfg.action_dim]))
    x = g.op("Mul", g.op("Sub", "obs", g.const(obs_mean)), g.const(obs_scale))
    if obs_clip is not None:
        x = g.op("Clip", x, g.const(-obs_clip), g.const(obs_clip))
    value_fold = {"scale": value_std, "shift": value_mean}  # ValueNorm's de-normalisation
    std = None if discrete else policy.std().detach().cpu().numpy()
    shift = _noise_shift(g, std)
    if isinstance(policy, MAT):
        rep, values = _encoder(g, x, cfg, value_fold)
        params = _decoder(g, rep, cfg, shift, agents)
    else:
        if isinstance(policy, MAPPO):
            values = _mappo_values(g, x, cfg, value_fold)
        else:
            values = _encoder(g, x, cfg, value_fold)[1]
        params = _decentralised_sample(g, _mlp(g, x, "mlp"), shift, discrete)
    head = ["logits"] if discrete else ["mean", "std"]
    g.op("Identity", values, outputs=["values"])
    if not discrete:
        g.op("Expand", g.const(std, "std"), g.op("Shape", params["mean"]), outputs=["std"])
    for name in ["actions", *(h for h in head if h != "std")]:
        g.op("Identity", params[name], outputs=[name])
    widths = {"actions": 1 if discrete else cfg.action_dim, **dict.fromkeys(head, cfg.action_dim)}
    outputs = [_value(name, ["batch", n, w]) for name, w in {**widths, "values": 1}.items()]
    graph = helper.make_graph(g.nodes, "mat_decode", inputs, outputs, g.initializers)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid("", OPSET)])
    model.ir_version = 10
    return model


def _encoder(g: GraphBuilder, x: str, cfg, value_fold: dict) -> tuple[str, str]:
    """mat_sdk.model.Encoder: rep [B, n, C] and de-normalised values [B, n, 1]."""
    x = g.gelu(g.linear(g.layer_norm(x, "encoder.obs_encoder.0"), "encoder.obs_encoder.1"))
    x = g.layer_norm(x, "encoder.ln")
    for b in range(cfg.n_block):
        block = f"encoder.blocks.{b}"
        q, k, v = g.qkv(x, f"{block}.attn", ("query", "key", "value"), two_d=False)
        attended = g.op("Attention", q, k, v, q_num_heads=cfg.n_head, kv_num_heads=cfg.n_head)
        x = g.layer_norm(g.op("Add", x, g.linear(attended, f"{block}.attn.proj")), f"{block}.ln1")
        x = g.layer_norm(g.op("Add", x, _mlp_block(g, x, f"{block}.mlp")), f"{block}.ln2")
    return x, _head(g, x, "encoder.head", **value_fold)


def _mlp_block(g: GraphBuilder, x: str, prefix: str, two_d: bool = False) -> str:
    return g.linear(g.gelu(g.linear(x, f"{prefix}.0", two_d)), f"{prefix}.2", two_d)


def _head(g: GraphBuilder, x: str, prefix: str, two_d: bool = False, scale=1.0, shift=0.0) -> str:
    x = g.layer_norm(g.gelu(g.linear(x, f"{prefix}.0", two_d)), f"{prefix}.2")
    return g.linear(x, f"{prefix}.3", two_d, scale, shift)


def _mlp(g: GraphBuilder, x: str, prefix: str, **value_fold) -> str:
    """mat_sdk.model.actor_mlp: LN, Linear, GELU, LN, Linear, GELU, LN, Linear."""
    x = g.gelu(g.linear(g.layer_norm(x, f"{prefix}.0"), f"{prefix}.1"))
    x = g.gelu(g.linear(g.layer_norm(x, f"{prefix}.3"), f"{prefix}.4"))
    return g.linear(g.layer_norm(x, f"{prefix}.6"), f"{prefix}.7", **value_fold)


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


def _decoder(g: GraphBuilder, rep: str, cfg, shift: str, agents: int | None):
    """mat_sdk.model.Decoder run agent by agent with caches: an ONNX `Loop` over any number of
    agents, or (`agents` given) the steps written out one after another for that count."""
    heads, width = cfg.n_head, cfg.n_embd
    discrete = cfg.action_type == "discrete"
    w = g.weights
    # ---- before the agent steps, for all agents at once: [B, n, ...] tensors they slice
    per_agent = {"rep": rep}
    for b in range(cfg.n_block):  # the second attention's queries come from rep alone
        weight, bias = _stream_queries(w, f"decoder.blocks.{b}.attn2", heads)
        per_agent[f"query2.{b}"] = g.dense(rep, weight, bias, False, f"query2.{b}")
    per_agent["shift"] = shift
    packed = g.op("Concat", *per_agent.values(), axis=-1)
    embed = w["decoder.action_encoder.0.weight"].T  # [token, C]
    batch = g.op("Shape", rep, end=1)
    start = embed[0] if discrete else w["decoder.action_encoder.0.bias"]  # agent 0's token
    width_1d = g.const([width], "width", np.int64)
    first = g.op("Expand", g.const(start[None], "start"), g.op("Concat", batch, width_1d, axis=0))
    empty = g.op(
        "ConstantOfShape",
        g.op("Concat", batch, g.const([1, 0, width], "cache", np.int64), axis=0),
        value=numpy_helper.from_array(np.zeros(1, np.float32)),
    )
    caches = [
        f"{b}.{attn}.{kind}"
        for b in range(cfg.n_block)
        for attn in ("attn1", "attn2")
        for kind in ("key", "value")
    ]
    step = _AgentStep(cfg, discrete, packed, list(per_agent), embed)
    if agents is None:
        chosen, params = _loop(g, step, first, [empty] * len(caches), caches)
    else:
        chosen, params = _unrolled(g, step, first, [empty] * len(caches), agents)
    if discrete:
        actions = g.op("Unsqueeze", g.op("Cast", chosen, to=FLOAT), g.const([2], "axis2", np.int64))
        return {"actions": actions, "logits": _mask(g, params)}
    return {"actions": chosen, "mean": params}


class _AgentStep:
    """One agent's decoder step on 2-D [B, C] activations; writes its nodes into a builder."""

    def __init__(self, cfg, discrete: bool, packed: str, parts: list[str], embed: np.ndarray):
        self.cfg, self.discrete, self.packed, self.parts, self.embed = (
            cfg, discrete, packed, parts, embed,
        )  # fmt: skip

    def __call__(self, g: GraphBuilder, index: str, embedded: str, past: list[str]):
        """-> (next agent's embedded token, present caches, chosen action, action params)."""
        cfg, w, heads, width = self.cfg, g.weights, self.cfg.n_head, self.cfg.n_embd
        mine = g.op("Gather", self.packed, index, axis=1)  # [B, K]: this agent's share
        sizes = [width] + [heads * width] * cfg.n_block + [cfg.action_dim]
        sizes = g.const(sizes, "sizes", np.int64)
        mine = dict(
            zip(
                self.parts,
                g.op("Split", mine, sizes, axis=-1, outputs=len(self.parts)),
                strict=True,
            )
        )
        x = g.layer_norm(g.gelu(embedded), "decoder.ln")
        present: list[str] = []
        for b in range(cfg.n_block):
            block, cache = f"decoder.blocks.{b}", past[4 * b : 4 * b + 4]
            weight, bias = _stream_queries(w, f"{block}.attn1", heads)
            queries = g.dense(x, weight, bias, True, f"{block}.attn1.queries")
            attended = _stream_attention(g, queries, x, f"{block}.attn1", cache[:2], heads, present)
            x = g.layer_norm(g.op("Add", x, attended), f"{block}.ln1")
            query = mine[f"query2.{b}"]
            attended = _stream_attention(g, query, x, f"{block}.attn2", cache[2:], heads, present)
            x = g.layer_norm(g.op("Add", mine["rep"], attended), f"{block}.ln2")
            x = g.layer_norm(g.op("Add", x, _mlp_block(g, x, f"{block}.mlp", True)), f"{block}.ln3")
        params = _head(g, x, "decoder.head", two_d=True)
        if self.discrete:
            chosen = g.op("ArgMax", g.op("Add", params, mine["shift"]), axis=-1, keepdims=0)
            embedded = g.op("Gather", g.const(self.embed[1:], "choices"), chosen, axis=0)
        else:
            chosen = g.op("Add", params, mine["shift"])
            bias = w["decoder.action_encoder.0.bias"]
            embedded = g.dense(chosen, self.embed, bias, True, "decoder.action_encoder")
        return embedded, present, chosen, params


def _loop(g: GraphBuilder, step: _AgentStep, first: str, empty: list[str], caches: list[str]):
    """The agent steps as the body of an ONNX `Loop`: any agent count. -> [B, n, ...] outputs."""
    body = GraphBuilder(g.weights, prefix="agent/")
    body.constants = g.constants  # the body reads the weights from the main graph (outer scope)
    past = [f"past.{c}" for c in caches]
    embedded, present, chosen, params = step(body, "i", "embedded", past)
    body.op("Identity", "cond", outputs=["cond_out"])
    cache_shape = ["batch", 1, "past", step.cfg.n_embd]
    act = step.cfg.action_dim
    body_inputs = [
        helper.make_tensor_value_info("i", INT64, []),
        helper.make_tensor_value_info("cond", TensorProto.BOOL, []),
        _value("embedded", ["batch", step.cfg.n_embd]),
        *(_value(p, cache_shape) for p in past),
    ]
    chosen_info = (
        helper.make_tensor_value_info(chosen, INT64, ["batch"])
        if step.discrete
        else _value(chosen, ["batch", act])
    )
    body_outputs = [
        helper.make_tensor_value_info("cond_out", TensorProto.BOOL, []),
        _value(embedded, ["batch", step.cfg.n_embd]),
        *(_value(p, cache_shape) for p in present),
        chosen_info,
        _value(params, ["batch", act]),
    ]
    loop_body = helper.make_graph(body.nodes, "agent_step", body_inputs, body_outputs)
    g.initializers += body.initializers
    agents = g.op("Squeeze", g.op("Shape", "obs", start=1, end=2))
    carried = [first, *empty]
    *_, chosen, params = g.op(
        "Loop", agents, g.const(True, "true", np.bool_), *carried,
        outputs=len(carried) + 2, body=loop_body,
    )  # fmt: skip
    params = g.op("Transpose", params, perm=[1, 0, 2])  # [n, B, A] -> [B, n, A]
    chosen = g.op("Transpose", chosen, perm=[1, 0] if step.discrete else [1, 0, 2])
    return chosen, params


def _unrolled(g: GraphBuilder, step: _AgentStep, first: str, past: list[str], agents: int):
    """The agent steps written out for exactly `agents` agents: no loop machinery at all."""
    embedded, chosen, params = first, [], []
    axis1 = g.const([1], "axis1", np.int64)
    for i in range(agents):
        embedded, past, choice, param = step(g, g.const(i, "agent", np.int64), embedded, past)
        chosen.append(g.op("Unsqueeze", choice, axis1))
        params.append(g.op("Unsqueeze", param, axis1))
    return g.op("Concat", *chosen, axis=1), g.op("Concat", *params, axis=1)


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
    """One agent's stream queries [B, H*C] attend over the cached stream plus its own entry
    `stream` [B, C]: ONNX `Attention` with H query heads sharing one key/value head of width C
    (the stream serves as both; scale already folded into the queries). Appends the caches."""
    width = g.weights[f"{attn}.proj.bias"].shape[0]
    queries = g.op("Reshape", queries, g.const([0, heads, 1, width], "heads", np.int64))
    entry = g.op("Reshape", stream, g.const([0, 1, 1, width], "entry", np.int64))
    mixed, *caches = g.op(
        "Attention", queries, entry, entry, "", *past,
        outputs=3, scale=1.0,
    )  # fmt: skip
    present += caches
    mixed = g.op("Reshape", mixed, g.const([0, heads * width], "flat", np.int64))
    weight, bias = _stream_output(g.weights, attn, heads)
    return g.dense(mixed, weight, bias, True, f"{attn}.out")
