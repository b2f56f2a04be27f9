"""`decode.onnx`: the whole control step in one ONNX Runtime call, composed from the two graphs.

    obs [B, n, obs_dim], noise [B, n, A] (, available [B, n, A]) ->
    actions, mean + std (continuous) or logits (discrete), values

The encoder runs once; for MAT an ONNX `Loop` then runs the KV-cached step graph once per
agent, sampling in the graph: continuous `mean + std * noise`, discrete
`argmax(logits + noise)` (pass Gumbel noise to sample, zeros for the deterministic action).
The graphs are inlined, not re-exported, so `encoder.onnx` and `decoder_step.onnx` stay the
single source of the network.
"""

from __future__ import annotations

import copy

import numpy as np
import onnx
from onnx import TensorProto, helper, numpy_helper

FLOAT, INT64, BOOL = TensorProto.FLOAT, TensorProto.INT64, TensorProto.BOOL


def _inline(graph: onnx.GraphProto, prefix: str, inputs: dict[str, str]):
    """The graph's nodes and initializers with every name prefixed, its inputs wired to `inputs`.

    Returns (nodes, initializers, {original output name: new name}).
    """
    names = dict(inputs)
    names.update({init.name: prefix + init.name for init in graph.initializer})
    for node in graph.node:
        names.update({out: prefix + out for out in node.output if out})
    nodes = []
    for node in graph.node:
        renamed = copy.deepcopy(node)
        renamed.name = prefix + node.name
        renamed.input[:] = [names.get(x, x) if x else x for x in node.input]
        renamed.output[:] = [names[x] if x else x for x in node.output]
        nodes.append(renamed)
    initializers = []
    for init in graph.initializer:
        renamed = copy.deepcopy(init)
        renamed.name = names[init.name]
        initializers.append(renamed)
    return nodes, initializers, {out.name: names[out.name] for out in graph.output}


def _const(name: str, value, dtype=np.int64) -> onnx.TensorProto:
    return numpy_helper.from_array(np.asarray(value, dtype=dtype), name)


def _value(name: str, elem: int, shape=None) -> onnx.ValueInfoProto:
    """A typed value; ONNX Runtime wants the Loop body's values at least with their rank."""
    return helper.make_tensor_value_info(name, elem, shape)


def build_decode(
    encoder: onnx.ModelProto, step: onnx.ModelProto, manifest: dict
) -> onnx.ModelProto:
    discrete = manifest["action"]["type"] == "discrete"
    size = manifest["action"]["size"]
    enc_nodes, enc_inits, enc_out = _inline(encoder.graph, "encoder/", {"obs": "obs"})
    nodes, inits = list(enc_nodes), list(enc_inits)
    inputs = [
        helper.make_tensor_value_info("obs", FLOAT, ["batch", "agents", manifest["obs_dim"]]),
        helper.make_tensor_value_info("noise", FLOAT, ["batch", "agents", size]),
    ]
    if discrete:
        inputs.append(helper.make_tensor_value_info("available", FLOAT, ["batch", "agents", size]))
    head = ["logits"] if discrete else ["mean", "std"]
    rep, values = enc_out["rep"], enc_out["values"]
    nodes.append(helper.make_node("Identity", [values], ["values"]))
    if manifest["kind"] == "decentralised":
        step_inputs = {"rep": rep, **({"available": "available"} if discrete else {})}
        step_nodes, step_inits, step_out = _inline(step.graph, "step/", step_inputs)
        nodes += step_nodes
        inits += step_inits
        nodes += _sample(step_out, "noise", "actions", discrete)
        nodes += [helper.make_node("Identity", [step_out[h]], [h]) for h in head]
    else:
        loop_nodes, loop_inits = _loop(step, manifest, rep, discrete, head)
        nodes += loop_nodes
        inits += loop_inits
    widths = {"actions": 1 if discrete else size, **dict.fromkeys(head, size), "values": 1}
    outputs = [_value(name, FLOAT, ["batch", "agents", w]) for name, w in widths.items()]
    graph = helper.make_graph(nodes, "mat_decode", inputs, outputs, inits)
    model = helper.make_model(
        graph, opset_imports=list(encoder.opset_import), ir_version=encoder.ir_version
    )
    return model


def _sample(step_out: dict[str, str], noise: str, action: str, discrete: bool) -> list:
    """actions = mean + std * noise, or argmax(logits + noise) as a float index [.., 1]."""
    if discrete:
        return [
            helper.make_node("Add", [step_out["logits"], noise], [action + "/perturbed"]),
            helper.make_node(
                "ArgMax", [action + "/perturbed"], [action + "/index"], axis=-1, keepdims=1
            ),
            helper.make_node("Cast", [action + "/index"], [action], to=FLOAT),
        ]
    return [
        helper.make_node("Mul", [step_out["std"], noise], [action + "/scaled"]),
        helper.make_node("Add", [step_out["mean"], action + "/scaled"], [action]),
    ]


def _loop(step: onnx.ModelProto, manifest: dict, rep: str, discrete: bool, head: list[str]):
    """Main-graph nodes that run the step graph once per agent inside an ONNX Loop."""
    size, token_size = manifest["action"]["size"], manifest["action"]["token_size"]
    model = manifest["model"]
    head_dim = model["n_embd"] // model["n_head"]
    caches = manifest["caches"]
    inits = [
        _const("decode/one", [1]),
        _const("decode/zero", [0]),
        _const("decode/two", [2]),
        _const("decode/one_axis", [1]),
        _const("decode/token_rest", [1, token_size]),
        _const("decode/cache_rest", [model["n_head"], 0, head_dim]),
        _const("decode/true", True, np.bool_),
    ]
    nodes = [
        helper.make_node("Shape", ["obs"], ["decode/obs_shape"]),
        helper.make_node(
            "Slice", ["decode/obs_shape", "decode/zero", "decode/one"], ["decode/batch"]
        ),
        helper.make_node(
            "Slice", ["decode/obs_shape", "decode/one", "decode/two"], ["decode/agents_1d"]
        ),
        helper.make_node("Squeeze", ["decode/agents_1d"], ["decode/agents"]),
        helper.make_node(
            "Concat", ["decode/batch", "decode/token_rest"], ["decode/token_shape"], axis=0
        ),
        helper.make_node(
            "ConstantOfShape",
            ["decode/token_shape"],
            ["decode/token_zeros"],
            value=_const("", [0.0], np.float32),
        ),
        helper.make_node(
            "Concat", ["decode/batch", "decode/cache_rest"], ["decode/cache_shape"], axis=0
        ),
        helper.make_node(
            "ConstantOfShape",
            ["decode/cache_shape"],
            ["decode/empty_cache"],
            value=_const("", [0.0], np.float32),
        ),
    ]
    if discrete:  # the first agent's token marks the start: [1, 0, ..., 0]
        start = np.zeros((1, 1, token_size), np.float32)
        start[..., 0] = 1.0
        inits.append(_const("decode/start", start, np.float32))
        nodes.append(
            helper.make_node("Add", ["decode/token_zeros", "decode/start"], ["decode/token0"])
        )
    else:
        nodes.append(helper.make_node("Identity", ["decode/token_zeros"], ["decode/token0"]))

    # ---- the body: one agent
    cache_shape = ["batch", model["n_head"], "past", head_dim]
    body_in = [
        _value("i", INT64, []),
        _value("cond", BOOL, []),
        _value("token", FLOAT, ["batch", 1, token_size]),
    ]
    body_in += [_value(f"in/{c['past']}", FLOAT, cache_shape) for c in caches]
    body = [
        helper.make_node("Unsqueeze", ["i", "decode/zero"], ["i1"]),
        helper.make_node("Add", ["i1", "decode/one"], ["i2"]),
        helper.make_node("Slice", [rep, "i1", "i2", "decode/one_axis"], ["rep_i"]),
        helper.make_node("Slice", ["noise", "i1", "i2", "decode/one_axis"], ["noise_i"]),
        helper.make_node("Identity", ["cond"], ["cond_out"]),
    ]
    wiring = {"rep": "rep_i", "token": "token", **{c["past"]: f"in/{c['past']}" for c in caches}}
    if discrete:
        body.append(
            helper.make_node("Slice", ["available", "i1", "i2", "decode/one_axis"], ["available_i"])
        )
        wiring["available"] = "available_i"
    step_nodes, step_inits, step_out = _inline(step.graph, "step/", wiring)
    body += step_nodes
    inits += step_inits  # outer scope: the body reads the weights from the main graph
    body += _sample(step_out, "noise_i", "action_i", discrete)
    if discrete:  # the next agent's token: [0, one-hot of this choice]
        inits += [
            _const("decode/last_axis", [-1]),
            _const("decode/depth", size),
            _const("decode/onehot_values", [0.0, 1.0], np.float32),
            _const("decode/start_pad", [0, 0, 1, 0, 0, 0]),
        ]
        body += [
            helper.make_node("Squeeze", ["action_i/index", "decode/last_axis"], ["index_i"]),
            helper.make_node(
                "OneHot", ["index_i", "decode/depth", "decode/onehot_values"], ["onehot_i"], axis=-1
            ),
            helper.make_node("Pad", ["onehot_i", "decode/start_pad"], ["token_out"]),
        ]
    else:
        body.append(helper.make_node("Identity", ["action_i"], ["token_out"]))
    body_out = [_value("cond_out", BOOL, []), _value("token_out", FLOAT, ["batch", 1, token_size])]
    body_out += [_value(step_out[c["present"]], FLOAT, cache_shape) for c in caches]
    widths = [1 if discrete else size, *(size for _ in head)]
    scans = ["action_i", *(step_out[h] for h in head)]
    body_out += [
        _value(name, FLOAT, ["batch", 1, w]) for name, w in zip(scans, widths, strict=True)
    ]
    loop_body = helper.make_graph(body, "agent_step", body_in, body_out)

    carried = ["decode/token0", *("decode/empty_cache" for _ in caches)]
    final = ["decode/final_token", *(f"decode/final/{c['present']}" for c in caches)]
    stacked = [f"decode/stacked/{name}" for name in ("actions", *head)]
    nodes.append(
        helper.make_node(
            "Loop", ["decode/agents", "decode/true", *carried], final + stacked, body=loop_body
        )
    )
    inits.append(_const("decode/squeeze_axis", [2]))
    for name, out in zip(stacked, ("actions", *head), strict=True):  # [n, B, 1, A] -> [B, n, A]
        nodes += [
            helper.make_node("Squeeze", [name, "decode/squeeze_axis"], [name + "/3d"]),
            helper.make_node("Transpose", [name + "/3d"], [out], perm=[1, 0, 2]),
        ]
    return nodes, inits
