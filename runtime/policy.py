"""`Policy`: an exported MAT bundle acting through ONNX Runtime, with numpy only (no torch).

    from mat_runtime import Policy
    policy = Policy.load("cheetah_onnx")                  # checks manifest + sha256 of graphs
    actions = policy.act(obs)                             # obs [n, obs_dim] or [B, n, obs_dim]
    actions, extra = policy.act(obs, deterministic=False, seed=0, return_values=True)

One control step is one ONNX Runtime call of `decode.onnx` (encoder + the agents' decoder
steps + action selection); sampling noise is drawn here and passed in, zero noise gives the
deterministic action. Everything that can be done once happens in `load`.

Input rules (each violation raises `InputError`, and the policy keeps serving):
- `obs` is `[n, obs_dim]` or `[B, n, obs_dim]`, with any n >= 1 the bundle allows (MAPPO's
  critic fixes n). Any real dtype is accepted and converted to float32 (float64 is the
  common case); values must be finite after that conversion.
- `available` (discrete policies only) has the shape of the logits, `[.., n, actions]`, truthy
  where an action may be chosen; every agent needs at least one.
- Sampling (`deterministic=False`) needs `seed=`: an int, or a `numpy.random.Generator` you
  keep between calls. There is no hidden global RNG, so runs are reproducible.

Thread-safety: `act` may be called from several threads on one `Policy` at once (ONNX
Runtime sessions are thread-safe and the call shares no mutable state). A
`numpy.random.Generator` passed as `seed` is not thread-safe: give each thread its own.
"""

from __future__ import annotations

import json
import math
import re
import threading
from pathlib import Path
from typing import Any

import numpy as np
import onnxruntime as ort

from mat_runtime.bundle import read_bundle
from mat_runtime.errors import BundleError, InputError
from mat_runtime.wiring import Wiring
from mat_runtime.wiring_schema import WiringSpec

# The oldest onnxruntime verified to run the graphs of each opset the exporter writes:
# `decode*.onnx` uses ONNX's `Attention` op (opset 24); 1.23.2 and older refuse the opset.
ONNXRUNTIME_FOR_OPSET = {24: "1.24.1"}
GRAPHS = ("decode", "step")  # one call per control step, or one per agent (`step.py`)
GRAPH = "decode.onnx"  # any agent count; `decode_nN.onnx`: unrolled for exactly N (faster)
# The most agents one call serves. Full attention's memory grows with n^2 (about 1.5 GB at
# 16,384 agents); far beyond it ONNX Runtime fails to allocate.
MAX_AGENTS = 16_384
_BOUND_CACHE = 32  # bound [B, n] shapes kept per thread
# ONNX Runtime's fused Add + LayerNorm kernel (SkipLayerNormalization) is faster at B = 1
# but slower with many rows (BENCHMARKS.md), so batches of BATCH_ROWS or more go to
# sessions built without that fusion.
BATCH_ROWS = 8
BATCH_DISABLED_OPTIMIZERS = ["SkipLayerNormFusion"]


def session(
    graph: bytes,
    threads: int = 1,
    providers: list[str] | None = None,
    batched: bool = False,
    spin: bool = False,
) -> ort.InferenceSession:
    """An ONNX Runtime session set up for control steps: sequential, `threads` intra-op
    threads, all graph optimisations (less `BATCH_DISABLED_OPTIMIZERS` when `batched`).

    `spin`: with `threads` > 1, the intra-op threads busy-wait for work between calls (ONNX
    Runtime's own default) instead of sleeping. Off here: a controller acts once per tick
    and idles between, and spinning threads would burn those cores (BENCHMARKS.md).

    Memory reuse is off: ONNX Runtime then gives every intermediate tensor its own buffer
    instead of planning which can share one. The tensors here are a few KB, and at B = 1 a
    step runs faster without the planner's bookkeeping (BENCHMARKS.md)."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = threads
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    options.enable_mem_reuse = False
    options.log_severity_level = 3  # warnings about unused initializers are not the user's
    options.add_session_config_entry("session.intra_op.allow_spinning", "1" if spin else "0")
    return ort.InferenceSession(
        graph,
        options,
        providers=providers or ["CPUExecutionProvider"],
        disabled_optimizers=BATCH_DISABLED_OPTIMIZERS if batched else None,
    )


class Policy:
    """A loaded bundle. Create with `Policy.load`; act with `act`."""

    def __init__(
        self,
        path: Path,
        manifest: dict[str, Any],
        sessions: dict[tuple[int | None, bool], ort.InferenceSession],
    ):
        self.path, self.manifest = path, manifest
        # by (the agent count a graph is unrolled for, None: any; batch of >= BATCH_ROWS)
        self._sessions = sessions
        action = manifest["action"]
        self.algo: str = manifest["algo"]
        self.env_id: str | None = manifest.get("env_id")
        # the robot it was trained on:
        # `mat_sdk.envs.make_team(env_id, faults=env_faults, **env_options)`
        self.env_faults: dict[str, str] = manifest.get("env_faults", {})
        self.env_options: dict[str, Any] = manifest.get("env_options", {})
        # the domain randomization it was trained under (`mat_sdk.envs.Randomization`), or None
        self.randomization: dict[str, Any] | None = manifest.get("randomization")
        self.obs_dim: int = int(manifest["obs_dim"])
        self.action_type: str = action["type"]
        self.action_size: int = int(action["size"])
        self.action_low, self.action_high = float(action["low"]), float(action["high"])
        self._low, self._high = np.float32(self.action_low), np.float32(self.action_high)
        self.min_agents: int = int(manifest["agents"]["min"])
        self.max_agents: int | None = manifest["agents"]["max"]
        self.discrete = self.action_type == "discrete"
        head = ["logits"] if self.discrete else ["mean", "std"]
        self._outputs = ["actions", *head, "values"]
        self._local = threading.local()  # each thread's bound buffers (`_Bound`)
        # discrete agents with fewer choices than the widest: their padding is never chosen
        choices = manifest["agents"].get("choices")
        self._own_choices = None
        if self.discrete and choices is not None:
            own = np.arange(self.action_size) < np.array(choices)[:, None]
            self._own_choices = own.astype(np.float32)  # [trained agents, action_size]
        wiring = manifest.get("wiring")
        if wiring is not None:
            where = str(path / "manifest.json")
            wiring = Wiring(WiringSpec.from_json(wiring, self.obs_dim, self.action_size, where))
        # how the arrays map onto the robot (`mat_runtime.wiring`); None for older bundles
        self.wiring: Wiring | None = wiring

    @classmethod
    def load(
        cls,
        path: str | Path,
        threads: int = 1,
        providers: list[str] | None = None,
        spin: bool = False,
        graph: str = "decode",
    ) -> Policy:
        """Verify the bundle (format, version, sha256 of each graph), then build the sessions.

        `graph="step"` decodes agent by agent through `encoder.onnx` and the KV-cached
        `decoder_step.onnx` instead of one `decode.onnx` call (`mat_runtime.step`: the same
        actions, and `stream` yields each agent's as it is decoded).

        `threads`: ONNX Runtime intra-op threads; 1 is fastest for MAT's small kernels and
        keeps the controller's other cores free. `providers`: ONNX Runtime execution providers
        (default CPU). `spin`: let the intra-op threads (threads > 1) busy-wait between calls
        instead of sleeping; off by default, for a controller that idles between ticks.
        """
        if not isinstance(threads, int) or isinstance(threads, bool) or threads < 1:
            raise InputError(f"threads must be an int >= 1, got {threads!r}")
        if not isinstance(spin, bool):
            raise InputError(f"spin must be True or False, got {spin!r}")
        if graph not in GRAPHS:
            raise InputError(f"graph must be one of {GRAPHS}, got {graph!r}")
        if graph == "step" and cls is Policy:
            from mat_runtime.step import StepPolicy

            return StepPolicy.load(path, threads, providers, spin)
        available = ort.get_available_providers()
        providers = list(providers or ["CPUExecutionProvider"])
        unknown = [p for p in providers if p not in available]
        if unknown:
            raise InputError(f"providers {unknown} are not available here; available: {available}")
        bundle = read_bundle(path, _decode_graphs)
        sessions = {}
        for name, data in bundle.graphs.items():
            entry, file = bundle.manifest["graphs"][name], bundle.path / name
            agents = entry.get("agents")
            for batched in (False, True):  # the same graph, two optimisation settings
                opened = _open_session(
                    file, entry["opset"], data, threads, providers, batched, spin
                )
                sessions[(agents, batched)] = opened
            _check_graph(file, opened, bundle.manifest, agents)
        return cls(bundle.path, bundle.manifest, sessions)

    def __repr__(self) -> str:
        agents = f"{self.min_agents}..{self.max_agents or 'any'}"
        return (
            f"Policy({str(self.path)!r}, algo={self.algo}, env={self.env_id}, "
            f"obs_dim={self.obs_dim}, {self.action_type} actions x{self.action_size}, "
            f"agents {agents})"
        )

    def describe(self) -> str:
        """What an integrator needs: the policy, and how to wire it to the robot."""
        trained = self.manifest["agents"].get("trained_counts") or [
            self.manifest["agents"].get("trained")
        ]
        lines = [repr(self), f"trained on agent counts {trained}"]
        if self.wiring is None:
            lines.append(
                "no wiring in this bundle (exported before it was recorded, or an env "
                "without actuators); re-export it with `mat export` to add it"
            )
        else:
            lines.append(self.wiring.describe())
        return "\n".join(lines)

    def act(
        self,
        obs,
        available=None,
        *,
        deterministic: bool = True,
        seed: int | np.random.Generator | None = None,
        return_values: bool = False,
        clip: bool = True,
        out: np.ndarray | None = None,
        out_extra: dict[str, np.ndarray] | None = None,
    ):
        """Actions for every agent: `[.., n, action_size]` floats (continuous, clipped to the
        action bounds) or `[.., n]` int64 choices (discrete); `..` is B when obs has a batch.

        `clip=False` returns continuous samples as drawn, i.e. what each next agent was
        conditioned on (what a rollout collector must store); the env clips them anyway.

        With `return_values=True` also returns a dict: `values` `[.., n]` (in return units)
        and the distribution, `mean`/`std` or masked `logits` `[.., n, action_size]`.

        `out` (and, with `return_values`, `out_extra`: a dict of arrays for some or all of
        those names) are caller-owned arrays of exactly those shapes to write into; `act`
        then returns them. A control loop that passes the same float32 obs buffer and
        `out` every tick allocates nothing per call (continuous policies; discrete ones
        without `available`): the graph's inputs and outputs are bound once per shape.
        """
        x = self._check_obs(obs)
        single = x.ndim == 2
        batch, n = (1, x.shape[0]) if single else x.shape[:2]
        bound = self._bound(batch, n)
        views = bound.single if single else bound.batched
        if x.dtype == np.float32:
            np.copyto(views["obs"], x)
        else:
            with np.errstate(over="ignore"):  # out-of-range values become inf: refused below
                np.copyto(views["obs"], x, casting="unsafe")
        self._fill_noise(views["noise"], deterministic, seed)
        if self.discrete:
            self._fill_available(views["available"], available)
        elif available is not None:
            raise InputError("`available` is for discrete policies; this one is continuous")
        bound.run()
        self._check_finite(bound.buffers["obs"], bound.buffers.get("obs_check"), single)
        if self.discrete:
            actions = views["choices"]
        elif not clip or "clipped_actions" not in views:
            actions = views["actions"]
        else:
            actions = views["clipped_actions"]
        clip_here = clip and not self.discrete and "clipped_actions" not in views
        # a bundle exported before the graph clipped: clip here
        actions = _deliver(actions, out, "out", np.int64 if self.discrete else np.float32)
        if clip_here:
            np.clip(actions, self._low, self._high, out=actions)
        if not return_values:
            return actions
        if out_extra is not None:
            if not isinstance(out_extra, dict):
                raise InputError(
                    f"out_extra must be a dict of arrays, got {type(out_extra).__name__}"
                )
            unknown = sorted(set(out_extra) - set(self._outputs[1:]), key=str)
            if unknown:
                raise InputError(
                    f"out_extra names {unknown}; this policy returns {self._outputs[1:]}"
                )
        extra = {}
        for name in self._outputs[1:]:
            given = None if out_extra is None else out_extra.get(name)
            extra[name] = _deliver(views[name], given, f"out_extra[{name!r}]", np.float32)
        return actions, extra

    # ---- input checks: each names the problem and what to do
    def _check_obs(self, obs) -> np.ndarray:
        try:
            array = np.asarray(obs)
        except ValueError as err:
            raise InputError(f"obs is not an array ({err})") from None
        if array.dtype.kind not in "fiub":
            raise InputError(f"obs must be numbers, got dtype {array.dtype}")
        if array.ndim not in (2, 3):
            one_agent = "; for a single agent pass obs[None]" if array.ndim == 1 else ""
            raise InputError(
                f"obs must be [n, obs_dim] or [B, n, obs_dim], got shape {array.shape}{one_agent}"
            )
        if array.shape[-1] != self.obs_dim:
            raise InputError(
                f"obs has {array.shape[-1]} features per agent; this policy takes {self.obs_dim} "
                f"(trained on {self.env_id}); is it the right env and one-hot id setting?"
            )
        n = array.shape[-2]
        if n == 0 or (array.ndim == 3 and array.shape[0] == 0):
            raise InputError(f"obs has no agents or no batch rows (shape {array.shape})")
        if n > MAX_AGENTS:
            raise InputError(f"got {n} agents; one call serves at most {MAX_AGENTS:,}")
        if n < self.min_agents or (self.max_agents is not None and n > self.max_agents):
            allowed = (
                f"exactly {self.max_agents}"
                if self.min_agents == self.max_agents
                else f"{self.min_agents}..{self.max_agents or 'any'}"
            )
            raise InputError(f"got {n} agents; this {self.algo} bundle serves {allowed}")
        return array

    @staticmethod
    def _check_finite(x: np.ndarray, obs_check, single: bool) -> None:
        """Refuse NaN or inf in obs, after the call: the graph sums all observations into
        `obs_check` (one kernel, cheaper than numpy's check), and only a non-finite sum (or
        a bundle without it) leads to the search for the agent."""
        if obs_check is not None and math.isfinite(obs_check):
            return
        bad = ~np.isfinite(x).all(axis=-1)
        if bad.any():  # else the sum merely overflowed
            row, agent = np.argwhere(bad)[0]
            where = f"agent {agent}" + ("" if single else f" of batch row {row}")
            raise InputError(f"obs of {where} contains NaN or inf (as float32); check the sensor")

    def _fill_available(self, buffer: np.ndarray, available) -> None:
        """Write `available` (None: every choice) as 1/0 into the graph's input `buffer`."""
        own = self._own_choices
        if own is not None and own.shape[0] != buffer.shape[-2]:
            own = None  # another agent count than the team's: no per-agent choice counts
        if available is None:
            buffer.fill(1.0)
            if own is not None:
                np.multiply(buffer, own, out=buffer)
            return
        mask = np.asarray(available)
        one_row = buffer.ndim == 3 and buffer.shape[0] == 1 and mask.shape == buffer.shape[1:]
        if mask.shape != buffer.shape and not one_row:
            raise InputError(f"available must have shape {buffer.shape}, got {mask.shape}")
        np.not_equal(mask, 0, out=buffer)
        if own is not None:
            np.multiply(buffer, own, out=buffer)
        blocked = ~buffer.any(axis=-1)
        if blocked.any():
            agent = int(np.argwhere(blocked)[0][-1])
            raise InputError(f"agent {agent} has no available action; at least one must be allowed")

    def _bound(self, batch: int, n: int) -> _Bound:
        """This thread's buffers bound to the graph for [batch, n], made once per shape."""
        cache = getattr(self._local, "bound", None)
        if cache is None:
            cache = self._local.bound = {}
        bound = cache.get((batch, n))
        if bound is None:
            if len(cache) >= _BOUND_CACHE:
                cache.clear()
            batched = batch >= BATCH_ROWS
            session = self._sessions.get((n, batched)) or self._sessions[(None, batched)]
            per_agent, one = (batch, n, self.action_size), (batch, n, 1)
            shapes = {
                "obs": (batch, n, self.obs_dim),
                "noise": per_agent,
                **({"available": per_agent} if self.discrete else {}),
            }
            for output in session.get_outputs():  # actions, mean + std or logits, values, ..
                name = output.name
                if name == "obs_check":
                    shapes[name] = ()
                elif name == "values" or (name == "actions" and self.discrete):
                    shapes[name] = one
                else:
                    shapes[name] = per_agent
            bound = cache[(batch, n)] = _Bound(session, shapes, self.discrete)
        return bound

    def _fill_noise(self, buffer: np.ndarray, deterministic: bool, seed) -> None:
        """Write the sampling noise into the graph's input `buffer` (zero: deterministic)."""
        if deterministic:
            if seed is not None:
                raise InputError(
                    "seed given for a deterministic call; pass deterministic=False to sample"
                )
            buffer.fill(0.0)
            return
        if seed is None:
            raise InputError(
                "sampling needs seed=: an int, or a numpy.random.Generator kept between calls"
            )
        if isinstance(seed, np.random.Generator):
            rng = seed
        elif isinstance(seed, (int, np.integer)) and not isinstance(seed, bool):
            if seed < 0:
                raise InputError(f"seed must be an int >= 0, got {seed}")
            rng = np.random.default_rng(int(seed))
        else:
            raise InputError(
                f"seed must be an int or numpy.random.Generator, got {type(seed).__name__}"
            )
        if not self.discrete:
            rng.standard_normal(dtype=np.float32, out=buffer)
            return
        rng.random(dtype=np.float32, out=buffer)  # uniform -> Gumbel, in place
        np.maximum(buffer, np.finfo(np.float32).tiny, out=buffer)
        np.log(buffer, out=buffer)
        np.negative(buffer, out=buffer)
        np.log(buffer, out=buffer)
        np.negative(buffer, out=buffer)


_KINDS = {"f": "float", "i": "integer"}


def _deliver(source: np.ndarray, out: np.ndarray | None, name: str, dtype) -> np.ndarray:
    """A copy of `source` (a bound buffer's view), or `source` written into the caller's `out`."""
    if out is None:
        return source.astype(dtype)  # always a copy
    if not isinstance(out, np.ndarray) or out.shape != source.shape:
        shape = getattr(out, "shape", type(out).__name__)
        raise InputError(f"{name} must be a numpy array of shape {source.shape}, got {shape}")
    dtype = np.dtype(dtype)
    fits = out.dtype.kind == dtype.kind and np.can_cast(dtype, out.dtype, "safe")
    if not fits or not out.flags.writeable:
        raise InputError(
            f"{name} must be a writeable {dtype} array (or a wider {_KINDS[dtype.kind]}), got "
            f"{out.dtype}" + ("" if out.flags.writeable else ", read-only")
        )
    np.copyto(out, source, casting="unsafe")
    return out


class _Bound:
    """A session's inputs and outputs bound once to fixed float32 buffers of one shape: a call
    copies its inputs in and the caller copies out what it keeps, so ONNX Runtime neither
    converts nor allocates them per call. One per thread: buffers are state.

    `batched` and `single` hold views of each buffer in the shapes `act` takes and returns,
    for a `[B, n, ..]` batch and for one `[n, ..]` step (B = 1); `choices` (discrete) and
    `values` drop the trailing 1."""

    def __init__(
        self, session: ort.InferenceSession, shapes: dict[str, tuple[int, ...]], discrete: bool
    ):
        self.session, self.binding = session, session.io_binding()
        self.buffers = {name: np.zeros(shape, np.float32) for name, shape in shapes.items()}
        inputs = {i.name for i in session.get_inputs()}
        for name, buffer in self.buffers.items():
            if name in inputs:
                self.binding.bind_cpu_input(name, buffer)
            else:
                address = buffer.ctypes.data
                self.binding.bind_output(name, "cpu", 0, np.float32, buffer.shape, address)
        self.batched = {name: b for name, b in self.buffers.items() if b.ndim == 3}
        self.batched["values"] = self.buffers["values"][..., 0]
        if discrete:
            self.batched["choices"] = self.buffers["actions"][..., 0]
        self.single = {name: view[0] for name, view in self.batched.items()}

    def run(self) -> None:
        """Run the graph on the input buffers; the outputs stay valid until this thread's next
        call with the same shape."""
        self.session.run_with_iobinding(self.binding)


def _version(text: str) -> tuple[int, ...]:
    """`1.24.1` (or `1.25.0.dev2026`) -> (1, 24, 1)."""
    return tuple(int(part) for part in re.findall(r"\d+", text)[:3])


def _open_session(file: Path, opset: int, data: bytes, *options) -> ort.InferenceSession:
    """A session for one graph, or `BundleError` saying why this onnxruntime cannot run it."""
    needed = max(
        (v for o, v in ONNXRUNTIME_FOR_OPSET.items() if opset >= o), key=_version, default=None
    )
    if needed and _version(ort.__version__) < _version(needed):
        raise BundleError(
            f"{file}: uses ONNX opset {opset}, which needs onnxruntime >= {needed}; this is "
            f"onnxruntime {ort.__version__}: pip install -U 'onnxruntime>={needed}'"
        )
    try:
        return session(data, *options)
    except Exception as error:  # onnxruntime's own Fail / InvalidProtobuf / ... types
        first = (str(error).splitlines() or [type(error).__name__])[0][:300]
        raise BundleError(
            f"{file}: onnxruntime {ort.__version__} cannot load this graph ({first}); "
            "is it damaged? re-export the bundle with `mat export`"
        ) from None


# Manifest fields the exporter also writes into every graph's metadata (hashed with it): the
# manifest must agree with them, so an edited manifest cannot make the runtime misread a graph.
DESCRIBED_BY_GRAPH = ("algo", "kind", "obs_dim", "action")


def _check_graph(file: Path, graph: ort.InferenceSession, manifest: dict, agents) -> None:
    """The graph's own inputs, outputs and metadata agree with the manifest the policy acts
    on."""
    metadata = graph.get_modelmeta().custom_metadata_map
    for key in DESCRIBED_BY_GRAPH:
        if key not in metadata:
            continue
        try:
            own = json.loads(metadata[key])
        except ValueError:
            own = None
        listed = manifest.get(key)
        if key == "action" and isinstance(own, dict) and isinstance(listed, dict):
            own = {k: own.get(k) for k in ("type", "size", "low", "high")}
            listed = {k: listed.get(k) for k in ("type", "size", "low", "high")}
        if own != listed:
            raise BundleError(
                f"{file.parent / 'manifest.json'}: {key} is {listed!r}, but {file.name} was "
                f"exported with {key} {own!r}; the manifest was edited: re-export the bundle"
            )
    discrete = manifest["action"]["type"] == "discrete"
    inputs = {i.name: i.shape for i in graph.get_inputs()}
    outputs = {o.name for o in graph.get_outputs()}
    wanted_in = {"obs", "noise", *(["available"] if discrete else [])}
    wanted_out = {"actions", "values", *(["logits"] if discrete else ["mean", "std"])}
    missing = sorted((wanted_in - set(inputs)) | (wanted_out - outputs))
    if missing:
        raise BundleError(
            f"{file}: has no {', '.join(missing)}, so it is not a {manifest['action']['type']} "
            "control-step graph (manifest action.type); re-export the bundle"
        )
    sizes = {"obs": ("obs_dim", manifest["obs_dim"])}
    sizes["noise"] = ("action.size", manifest["action"]["size"])
    for name, (field, size) in sizes.items():
        shape = inputs[name]
        count = shape[1] if len(shape) == 3 else None
        if len(shape) != 3 or shape[2] != size or (isinstance(count, int) and count != agents):
            expected = f"[batch, {agents or 'agents'}, {size}]"
            raise BundleError(
                f"{file}: input {name} has shape {shape}, but the manifest ({field}, the graph's "
                f"agents) says {expected}; re-export the bundle"
            )
        if agents is not None and count != agents:
            raise BundleError(
                f"{file}: is listed for {agents} agents, but its input {name} has shape {shape}; "
                "re-export the bundle"
            )


def _decode_graphs(manifest: dict) -> list[str]:
    """decode.onnx, plus the graphs specialised to one agent count that the bundle lists."""
    graphs = manifest.get("graphs", {})
    specialised = [
        name
        for name, entry in graphs.items()
        if name.startswith("decode_n") and isinstance(entry, dict) and entry.get("agents")
    ]
    return [GRAPH, *specialised]
