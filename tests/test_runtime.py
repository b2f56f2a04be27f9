"""mat_runtime: parity with the torch policy, sampling, loud errors, threads, no torch."""

import json
import os
import re
import subprocess
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import make_checkpoint

import mat_runtime
from mat_export import export
from mat_runtime import BundleError, InputError, Policy, loop
from mat_runtime.wiring_schema import WiringSpec
from mat_sdk.envs import Trusted, make_team
from mat_sdk.evaluation.episodes import CheckpointPolicy
from tests.recipes import with_examples

COUNTS = (1, 2, 3, 6, 17, 64)  # 2 and 3: the trained counts, served by decode_nN.onnx


@pytest.fixture(scope="module")
def bundles(tmp_path_factory):
    """(checkpoint, bundle) per policy kind; exported once for the module."""
    root = tmp_path_factory.mktemp("runtime")
    recipes = {
        "mat": ("hopper-2x2", "mat", {"n_block": 2, "n_head": 2}),
        "mat-discrete": ("coordination-3", "mat", {}),
        "mat-window": ("hopper-2x2", "mat", {"attention_window": 3}),  # 17, 64: past it
        "mat-dec": ("hopper-2x2", "mat-dec", {}),
        "mappo": ("coordination-3", "mappo", {}),
        "happo": ("hopper-2x2", "happo", {}),
    }
    made = {}
    for name, (env_id, algo, options) in recipes.items():
        ckpt = make_checkpoint(root / f"{name}.pt", env_id, algo, **options)
        export(ckpt, root / name, agent_counts=(1, 3))
        made[name] = (ckpt, root / name)
    return made


def _obs(policy, n, batch=None, seed=0):
    shape = (n, policy.obs_dim) if batch is None else (batch, n, policy.obs_dim)
    return 2.0 * np.random.default_rng(seed).standard_normal(shape)  # float64, as users pass


def _torch_actions(loaded: CheckpointPolicy, obs: np.ndarray) -> np.ndarray:
    return loaded.act(obs[None] if obs.ndim == 2 else obs)


@pytest.mark.parametrize("name", ["mat", "mat-discrete", "mat-window", "mat-dec", "mappo", "happo"])
def test_deterministic_actions_equal_the_torch_policy(bundles, name):
    ckpt, bundle = bundles[name]
    policy, loaded = Policy.load(bundle), CheckpointPolicy.from_checkpoint(ckpt)
    counts = {"mappo": (3,), "happo": (2,)}.get(name, COUNTS)
    for n in counts:
        obs = _obs(policy, n)
        got, expected = policy.act(obs), _torch_actions(loaded, obs)[0]
        if policy.discrete:
            assert got.shape == (n,) and got.dtype == np.int64
            np.testing.assert_array_equal(got, expected[:, 0].astype(np.int64))
        else:
            assert got.shape == (n, policy.action_size) and got.dtype == np.float32
            assert np.abs(got - np.clip(expected, -1, 1)).max() <= 1e-5, n


def test_batched_values_and_distribution_match_torch(bundles):
    ckpt, bundle = bundles["mat"]
    policy, loaded = Policy.load(bundle), CheckpointPolicy.from_checkpoint(ckpt)
    obs = _obs(policy, 6, batch=4)
    actions, extra = policy.act(obs, return_values=True)
    with torch.no_grad():
        x = torch.from_numpy(loaded.obs_norm.normalize(obs))
        means, values = loaded.policy.action_params(x, torch.from_numpy(extra["mean"]))
    assert actions.shape == (4, 6, policy.action_size) and extra["values"].shape == (4, 6)
    assert np.abs(extra["mean"] - means.numpy()).max() <= 1e-5
    # values come out in return units: the checkpoint's ValueNorm is folded in
    payload = torch.load(ckpt, weights_only=True)
    scale = payload["value_norm"]
    mean = (scale["running_mean"] / scale["debiasing_term"].clamp_min(1e-5)).item()
    mean_sq = (scale["running_mean_sq"] / scale["debiasing_term"].clamp_min(1e-5)).item()
    expected = values.numpy()[..., 0] * np.sqrt(max(mean_sq - mean**2, 1e-2)) + mean
    assert np.abs(extra["values"] - expected).max() <= 1e-4


def test_discrete_sampling_follows_the_torch_joint_distribution(bundles):
    """20,000 sampled joint choices vs the exact joint probabilities from torch's log-probs."""
    ckpt, bundle = bundles["mat-discrete"]
    policy, loaded = Policy.load(bundle), CheckpointPolicy.from_checkpoint(ckpt)
    samples = 20_000
    obs = np.repeat(_obs(policy, 3)[None], samples, axis=0)
    available = np.ones((samples, 3, 3), bool)
    available[:, 2, 0] = False  # the third agent may not pick option 0
    choices = policy.act(obs, available, deterministic=False, seed=7)
    assert (choices[:, 2] != 0).all()
    joints = np.array(np.meshgrid(*[range(3)] * 3, indexing="ij")).reshape(3, -1).T  # all 27
    with torch.no_grad():
        x = torch.from_numpy(loaded.obs_norm.normalize(obs[: len(joints)]))
        log_prob, _, _ = loaded.policy.evaluate_actions(
            x,
            torch.from_numpy(joints[:, :, None]).float(),
            torch.from_numpy(available[: len(joints)]).float(),
        )
    exact = log_prob.sum((1, 2)).exp().numpy()
    codes = choices @ np.array([9, 3, 1])
    empirical = np.bincount(codes, minlength=27) / samples
    assert abs(exact.sum() - 1) < 1e-4
    assert 0.5 * np.abs(empirical - exact).sum() < 0.02  # total variation distance
    assert not np.allclose(exact, exact[0])  # a distribution worth testing: not uniform


def test_continuous_sampling_follows_the_torch_distribution(bundles):
    """Runtime samples, scored by torch teacher-forced on those same samples: z ~ N(0, 1)."""
    ckpt, bundle = bundles["mat"]
    policy, loaded = Policy.load(bundle), CheckpointPolicy.from_checkpoint(ckpt)
    obs = np.repeat(_obs(policy, 6)[None], 5000, axis=0)
    rng = np.random.default_rng(3)
    actions = policy.act(obs, deterministic=False, seed=rng, clip=False)  # as conditioned on
    assert np.abs(actions).max() > 1.0  # so clip=False really is unclipped
    with torch.no_grad():
        x = torch.from_numpy(loaded.obs_norm.normalize(obs))
        means, _ = loaded.policy.action_params(x, torch.from_numpy(actions))
        std = loaded.policy.std().numpy()
    z = (actions - means.numpy()) / std
    assert abs(z.mean()) < 0.05 and abs(z.std() - 1) < 0.05
    first_agent_spread = actions[:, 0].std() / std.mean()
    assert 0.9 < first_agent_spread < 1.1  # agent 0 has no predecessor: pure N(mean, std)


def test_seeds_make_sampling_reproducible(bundles):
    policy = Policy.load(bundles["mat"][1])
    obs = _obs(policy, 6)
    first = policy.act(obs, deterministic=False, seed=1)
    np.testing.assert_array_equal(first, policy.act(obs, deterministic=False, seed=1))
    assert not np.array_equal(first, policy.act(obs, deterministic=False, seed=2))
    rng = np.random.default_rng(5)
    a, b = (policy.act(obs, deterministic=False, seed=rng) for _ in range(2))
    assert not np.array_equal(a, b)  # a Generator advances between calls
    np.testing.assert_array_equal(policy.act(obs), policy.act(obs.astype(np.float32)))


def test_results_are_the_callers_own(bundles):
    """The runtime reuses its buffers between calls; what it returned must not change."""
    policy = Policy.load(bundles["mat"][1])
    obs = _obs(policy, 6)
    for clip in (True, False):
        actions, extra = policy.act(obs, deterministic=False, seed=1, clip=clip, return_values=True)
        kept = (actions.copy(), {name: value.copy() for name, value in extra.items()})
        policy.act(3 * obs, deterministic=False, seed=2, clip=clip, return_values=True)
        np.testing.assert_array_equal(actions, kept[0])
        for name, value in extra.items():
            np.testing.assert_array_equal(value, kept[1][name], err_msg=name)


# Run in a process of its own (torch blocked, no test machinery) so that nothing else
# allocates while tracemalloc watches: per call mode, the bytes left allocated and the
# allocations left per file over 10,000 calls at 6 agents, and the peak bytes above the start
# over 100 calls at 160 agents, where every array a call would make outgrows NumPy's cache
# of small buffers (1 KiB) and is seen.
_ALLOCATIONS = """
import json, sys, tracemalloc
sys.modules["torch"] = None
import numpy as np
from mat_runtime import Policy

policy = Policy.load(sys.argv[1])
rng = np.random.default_rng(0)

def calls(n):
    obs = rng.standard_normal((n, policy.obs_dim)).astype(np.float32)
    shape = (n,) if policy.discrete else (n, policy.action_size)
    out = np.zeros(shape, np.int64 if policy.discrete else np.float32)
    heads = ["logits"] if policy.discrete else ["mean", "std"]
    extra = {h: np.zeros((n, policy.action_size), np.float32) for h in heads}
    extra["values"] = np.zeros(n, np.float32)
    return {
        "deterministic": lambda: policy.act(obs, out=out),
        "sampled": lambda: policy.act(obs, deterministic=False, seed=rng, out=out),
        "with values": lambda: policy.act(obs, out=out, return_values=True, out_extra=extra),
        "plain act": lambda: policy.act(obs, return_values=True),
    }

def traced(call, count, warm=100):
    tracemalloc.start()
    for _ in range(warm):
        call()
    before = tracemalloc.take_snapshot()
    start, _ = tracemalloc.get_traced_memory()
    tracemalloc.reset_peak()
    for _ in range(count):
        call()
    end, peak = tracemalloc.get_traced_memory()
    after = tracemalloc.take_snapshot()
    tracemalloc.stop()
    left = [s.count_diff for s in after.compare_to(before, "filename")
            if s.count_diff > 0 and "tracemalloc" not in s.traceback[0].filename]
    return end - start, max(left, default=0), peak - start

traced(calls(6)["deterministic"], 1000)  # ORT's bindings keep objects from the first traced calls
report = {mode: list(traced(call, 2_000)[:2])  # the plain call's copies: its peak only
          for mode, call in calls(6).items() if mode != "plain act"}
for mode, call in calls(160).items():
    report.setdefault(mode, [None, None]).append(traced(call, 100, warm=10)[2])
print(json.dumps(report))
"""


@pytest.mark.parametrize("name", ["mat", pytest.param("mat-discrete", marks=pytest.mark.slow)])
def test_acting_into_callers_arrays_allocates_nothing_per_call(bundles, name):
    policy = Policy.load(bundles[name][1])
    rng = np.random.default_rng(0)
    obs = rng.standard_normal((6, policy.obs_dim)).astype(np.float32)
    out = np.zeros((6,) if policy.discrete else (6, policy.action_size), policy.act(obs).dtype)
    expected = policy.act(obs, return_values=True)
    extra = {head: np.zeros_like(value) for head, value in expected[1].items()}
    assert policy.act(obs, out=out, return_values=True, out_extra=extra) == (out, extra)
    np.testing.assert_array_equal(out, expected[0])
    for head, value in expected[1].items():
        np.testing.assert_array_equal(extra[head], value, err_msg=head)

    run = subprocess.run(
        [sys.executable, "-c", _ALLOCATIONS, str(bundles[name][1])],
        capture_output=True,
        text=True,
        check=True,
    )
    report = json.loads(run.stdout)
    plain_peak = report.pop("plain act")[2]
    one_array = 160 * policy.action_size * 4  # one [160, action_size] float32 result
    assert plain_peak > one_array  # the plain call's copies are seen ...
    for mode, (left, most_left_by_a_file, peak) in report.items():
        assert left < 2048 and most_left_by_a_file < 10, (mode, report)  # none per call
        assert peak < 1024 < one_array, (mode, peak)  # ... and the out= calls make none


def test_caller_arrays_of_the_wrong_kind_are_refused(bundles):
    policy = Policy.load(bundles["mat"][1])
    obs, shape = _obs(policy, 3), (3, policy.action_size)
    for out, problem in (
        (np.zeros((3, 1), np.float32), f"out must be a numpy array of shape {shape}, got (3, 1)"),
        (np.zeros(shape, np.int32), "out must be a writeable float32 array (or a wider float), "
         "got int32"),
        ([[0.0] * shape[1]] * 3, f"out must be a numpy array of shape {shape}, got list"),
        *((np.zeros(shape, kind), f"got {np.dtype(kind)}")
          for kind in (np.complex64, np.float16, object)),
    ):  # fmt: skip
        with pytest.raises(InputError, match=re.escape(problem)):
            policy.act(obs, out=out)
    assert policy.act(obs, out=np.zeros(shape, np.float64)).dtype == np.float64  # wider is fine
    with pytest.raises(InputError, match=re.escape("out_extra['values'] must be a numpy array")):
        policy.act(obs, return_values=True, out_extra={"values": np.zeros(4, np.float32)})
    with pytest.raises(InputError, match="out_extra must be a dict of arrays, got list"):
        policy.act(obs, return_values=True, out_extra=[np.zeros(3, np.float32)])
    with pytest.raises(InputError, match=r"out_extra names \['value'\]; this policy returns"):
        policy.act(obs, return_values=True, out_extra={"value": np.zeros(3, np.float32)})
    with pytest.raises(InputError, match="one call serves at most 16,384"):
        policy.act(np.zeros((65_536, policy.obs_dim), np.float32))
    assert policy.act(obs).shape == shape  # and it keeps serving


def test_bad_input_raises_clear_errors_and_the_policy_keeps_serving(bundles):
    policy = Policy.load(bundles["mat"][1])
    discrete = Policy.load(bundles["mat-discrete"][1])
    mappo = Policy.load(bundles["mappo"][1])
    good = _obs(policy, 6)
    expected = policy.act(good)
    nan = good.copy()
    nan[4, 2] = np.nan
    batch_inf = _obs(policy, 6, batch=3)
    batch_inf[1, 2, 0] = -np.inf
    bad_calls = [
        (lambda: policy.act(good[:, :-1]), "features per agent"),
        (lambda: policy.act(good[0]), r"for a single agent pass obs\[None\]"),
        (lambda: policy.act(good[None, None]), "shape"),
        (lambda: policy.act(np.zeros((0, policy.obs_dim))), "no agents"),
        (lambda: policy.act(nan), "agent 4"),
        (lambda: policy.act(np.full_like(good, 1e39)), "inf"),
        (lambda: policy.act(batch_inf), "agent 2 of batch row 1"),
        (lambda: policy.act(good.astype(str)), "numbers"),
        (lambda: policy.act(good, deterministic=False), "seed"),
        (lambda: policy.act(good, seed=3), "deterministic=False"),
        (lambda: policy.act(good, deterministic=False, seed="x"), "seed must be"),
        (lambda: policy.act(good, np.ones((6, 1))), "discrete"),
        (lambda: discrete.act(_obs(discrete, 3), np.zeros((3, 3))), "no available action"),
        (lambda: discrete.act(_obs(discrete, 3), np.ones((3, 2))), "available must have shape"),
        (lambda: mappo.act(_obs(mappo, 2)), "exactly 3"),
    ]
    for call, message in bad_calls:
        with pytest.raises(InputError, match=message):
            call()
        np.testing.assert_array_equal(policy.act(good), expected)  # still serving
    assert issubclass(InputError, ValueError)
    huge = np.full_like(good, 3e38)  # finite in float32, but their sum overflows: still served
    assert np.isfinite(policy.act(huge)).all()


def test_a_bundle_exported_before_the_graph_checked_and_clipped_still_serves(bundles, tmp_path):
    """Older `decode*.onnx` graphs have no `clipped_actions` / `obs_check` outputs: the
    runtime then clips and checks obs with numpy, with the same results."""
    import hashlib
    import shutil

    import onnx

    source = bundles["mat"][1]
    old = tmp_path / "old"
    shutil.copytree(source, old)
    manifest = json.loads((old / "manifest.json").read_text())
    dropped = {"clipped_actions", "obs_check"}
    for name, entry in manifest["graphs"].items():
        if not name.startswith("decode"):
            continue
        model = onnx.load(old / name)
        graph = model.graph
        kept = [node for node in graph.node if not dropped & set(node.output)]
        del graph.node[:]
        graph.node.extend(kept)
        outputs = [o for o in graph.output if o.name not in dropped]
        del graph.output[:]
        graph.output.extend(outputs)
        onnx.save(model, old / name)
        entry["outputs"] = [o.name for o in outputs]
        entry["sha256"] = hashlib.sha256((old / name).read_bytes()).hexdigest()
    (old / "manifest.json").write_text(json.dumps(manifest))

    new, before = Policy.load(source), Policy.load(old)
    assert "obs_check" not in before._bound(1, 3).buffers
    for n in (3, 6):  # decode_n3.onnx and decode.onnx
        obs = _obs(new, n, batch=2, seed=n)
        np.testing.assert_array_equal(before.act(obs), new.act(obs))
        raw = new.act(obs, deterministic=False, seed=1, clip=False)
        assert np.abs(raw).max() > 1  # so the clip has something to do
        for clip in (True, False):
            got = before.act(obs, deterministic=False, seed=1, clip=clip)
            np.testing.assert_array_equal(got, new.act(obs, deterministic=False, seed=1, clip=clip))
        obs[1, n - 1, 3] = np.nan
        with pytest.raises(InputError, match=f"agent {n - 1} of batch row 1"):
            before.act(obs)


def test_broken_bundles_are_refused_before_loading(bundles, tmp_path):
    import shutil

    source = bundles["mat"][1]
    cases = {
        "missing": lambda d: shutil.rmtree(d),
        "no manifest": lambda d: (d / "manifest.json").unlink(),
        "missing graph": lambda d: (d / "decode.onnx").unlink(),
        "modified graph": lambda d: (d / "decode.onnx").write_bytes(
            (d / "decode.onnx").read_bytes()[:-1] + b"\0"
        ),
        "future version": lambda d: _edit_manifest(d, version=99),
        "not a bundle": lambda d: _edit_manifest(d, format="something-else"),
        "bad json": lambda d: (d / "manifest.json").write_text("{"),
    }
    messages = {
        "missing": "no such bundle",
        "no manifest": "no manifest.json",
        "missing graph": "missing",
        "modified graph": "sha256",
        "future version": "version 99",
        "not a bundle": "format",
        "bad json": "JSON",
    }
    for case, damage in cases.items():
        target = tmp_path / case.replace(" ", "_")
        shutil.copytree(source, target)
        damage(target)
        with pytest.raises(BundleError, match=messages[case]):
            Policy.load(target)
    assert issubclass(BundleError, OSError)
    with pytest.raises(BundleError, match="a file, not a bundle directory; pass its directory"):
        Policy.load(source / "manifest.json")
    with pytest.raises(InputError, match="not available"):
        Policy.load(source, providers=["NoSuchExecutionProvider"])


@pytest.mark.slow
def test_loading_while_an_export_replaces_the_bundle_never_fails(bundles, tmp_path):
    """`mat export --force` swaps a finished bundle in while a controller may be loading it:
    a load sees the old bundle or the new one, whole."""
    import shutil

    from mat_sdk.common import files

    target = tmp_path / "bundle"
    shutil.copytree(bundles["mat"][1], target)
    done, failures = threading.Event(), []

    def replace_again_and_again():
        while not done.is_set():
            staging = tmp_path / f".staging-{time.monotonic_ns()}"
            source = bundles["mat-dec" if len(failures) % 2 else "mat"][1]
            shutil.copytree(source, staging)
            files.replace_directory(staging, target)

    exporter = threading.Thread(target=replace_again_and_again)
    exporter.start()
    try:
        for _ in range(60):
            try:
                Policy.load(target)
            except BundleError as error:
                failures.append(error)
    finally:
        done.set()
        exporter.join()
    assert not failures, failures[:3]


@pytest.mark.parametrize("name", ["mat", "mat-discrete", "mat-window"])
def test_the_step_path_decodes_agent_by_agent_equal_to_decode_onnx(bundles, name):
    """`Policy.load(bundle, graph="step")`: encoder.onnx, then decoder_step.onnx per agent with
    the KV caches; the same actions, values and distributions as one decode.onnx call, and
    `stream` yields them agent by agent."""
    whole = Policy.load(bundles[name][1])
    stepped = Policy.load(bundles[name][1], graph="step")
    assert isinstance(stepped, mat_runtime.StepPolicy)
    for n in (1, 2, 3, 6, 17):
        obs = _obs(whole, n, seed=n)
        np.testing.assert_allclose(stepped.act(obs), whole.act(obs), atol=1e-5)
        kwargs = {"deterministic": False, "seed": 7, "return_values": True}
        (a, extra), (b, theirs) = stepped.act(obs, **kwargs), whole.act(obs, **kwargs)
        np.testing.assert_allclose(a, b, atol=1e-5)
        for key in theirs:
            np.testing.assert_allclose(extra[key], theirs[key], rtol=1e-5, atol=1e-4)
        streamed = list(stepped.stream(obs, deterministic=False, seed=7))
        assert [agent for agent, _ in streamed] == list(range(n))
        np.testing.assert_allclose(np.stack([action for _, action in streamed]), a, atol=1e-6)
    batch = _obs(whole, 3, batch=4)
    np.testing.assert_allclose(stepped.act(batch), whole.act(batch), atol=1e-5)


def test_the_step_path_is_for_autoregressive_bundles(bundles):
    for name in ("mat-dec", "mappo", "happo"):
        with pytest.raises(BundleError, match="decoding agent by agent is for MAT bundles"):
            Policy.load(bundles[name][1], graph="step")
    with pytest.raises(InputError, match="graph must be one of"):
        Policy.load(bundles["mat"][1], graph="steps")


def test_discrete_agents_with_fewer_choices_never_take_their_padding(tmp_path):
    """MPE's speaker has 3 choices, its listener 5: the bundle records each agent's count and
    the runtime masks the speaker's two padding choices, also without an `available` mask."""
    with_examples()
    ckpt = make_checkpoint(tmp_path / "c.pt", "mpe_envs:speaker_listener")
    manifest = export(Trusted(ckpt), tmp_path / "bundle", agent_counts=(1, 2))
    assert manifest["agents"]["choices"] == [3, 5]
    policy = Policy.load(tmp_path / "bundle")
    obs = 3.0 * np.random.default_rng(0).standard_normal((500, 2, policy.obs_dim))
    choices = policy.act(obs, deterministic=False, seed=0)
    assert choices[:, 0].max() <= 2 and choices[:, 1].max() >= 3
    run = subprocess.run(
        [sys.executable, "examples/controller.py", str(tmp_path / "bundle"), "--seconds", "0.3",
         "--warmup", "0", "--trust-env-code"],
        capture_output=True, text=True, cwd=Path(__file__).parents[1],
        env={**os.environ, "PYTHONPATH": "examples"},
    )  # fmt: skip
    assert run.returncode == 0, run.stderr


def _edit_manifest(directory, **fields):
    manifest = json.loads((directory / "manifest.json").read_text())
    manifest.update(fields)
    (directory / "manifest.json").write_text(json.dumps(manifest))


def test_spinning_is_a_choice_at_load_and_off_by_default(bundles):
    bundle = bundles["mat"][1]
    obs = _obs(Policy.load(bundle), 6)
    expected = Policy.load(bundle).act(obs)
    for spin, entry in ((None, "0"), (False, "0"), (True, "1")):
        options = {} if spin is None else {"spin": spin}
        policy = Policy.load(bundle, threads=2, **options)
        for opened in policy._sessions.values():
            settings = opened.get_session_options()
            assert settings.get_session_config_entry("session.intra_op.allow_spinning") == entry
        assert np.allclose(policy.act(obs), expected, atol=1e-6)  # the same actions either way
    with pytest.raises(InputError, match="spin must be True or False, got 'yes'"):
        Policy.load(bundle, spin="yes")


def test_one_policy_serves_several_threads(bundles):
    policy = Policy.load(bundles["mat"][1])
    inputs = [_obs(policy, n, seed=n) for n in (1, 2, 6, 17) * 3]
    expected = [policy.act(obs) for obs in inputs]
    sampled = [policy.act(obs, deterministic=False, seed=i) for i, obs in enumerate(inputs)]
    failures = []

    def worker(offset):
        for round_ in range(30):
            i = (offset + round_) % len(inputs)
            if not np.array_equal(policy.act(inputs[i]), expected[i]):
                failures.append(("deterministic", i))
            if not np.array_equal(policy.act(inputs[i], deterministic=False, seed=i), sampled[i]):
                failures.append(("sampled", i))

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert not failures


def _run_example(name: str, *args: str) -> str:
    """Run examples/NAME as a user would; its stdout, or the test fails with its stderr."""
    script = Path(__file__).parents[1] / "examples" / name
    result = subprocess.run(
        [sys.executable, str(script), *args], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    return result.stdout


@pytest.mark.parametrize("name", ["mat", "mat-discrete"])
def test_controller_example_runs_without_torch(bundles, name):
    """examples/controller.py (which blocks torch itself) on a robot and on the game."""
    out = _run_example("controller.py", str(bundles[name][1]), "--rate", "50", "--seconds", "0.4")
    assert "20 ticks in" in out and "p99.9" in out and "episode returns:" in out, out


def test_the_loop_keeps_its_rate_measures_every_tick_and_counts_overruns():
    calls = {"act": 0, "step": 0}
    ticks = loop.run(
        lambda: calls.__setitem__("act", calls["act"] + 1),
        lambda: calls.__setitem__("step", calls["step"] + 1),
        rate=200,
        seconds=0.25,
        warmup=0.05,
    )
    assert calls == {"act": 60, "step": 60} and len(ticks.act_seconds) == 50
    assert ticks.late < 5 and 0.24 < ticks.elapsed < 0.5  # a late tick is a 5 ms stall
    assert set(ticks.percentiles()) == {"p50", "p99", "p99.9", "max"}
    assert "50 ticks in" in ticks.summary() and f"late ticks: {ticks.late};" in ticks.summary()
    slow = loop.run(lambda: time.sleep(0.006), lambda: None, rate=200, seconds=0.1, warmup=0)
    assert slow.late == 20 and slow.percentiles()["p50"] > 5000  # every 5 ms tick overran
    with pytest.raises(ValueError, match="rate and seconds must be > 0"):
        loop.run(lambda: None, lambda: None, rate=0)


def test_realtime_requests_say_what_happened():
    allowed = sorted(os.sched_getaffinity(0))
    try:
        assert loop.realtime(cpu=allowed[0]) == [f"pinned to CPU {allowed[0]}"]
        (note,) = loop.realtime(cpu=10_000)
        assert note.startswith("not pinned to CPU 10000") and "allowed CPUs" in note
    finally:
        os.sched_setaffinity(0, allowed)
    # SCHED_FIFO itself is left to a subprocess: granted, it would outlive this test
    script = "from mat_runtime import loop; print(loop.realtime(fifo=1)[0])"
    note = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, check=True
    ).stdout
    assert note.startswith(("SCHED_FIFO at priority 1", "SCHED_FIFO not permitted: run as root"))


def test_keep_awake_spins_at_the_lowest_priority_on_its_core_until_stopped():
    cpu = sorted(os.sched_getaffinity(0))[-1]
    spinner = loop.keep_awake(cpu)
    try:
        assert spinner.poll() is None  # running
        assert os.sched_getscheduler(spinner.pid) == os.SCHED_IDLE
        assert os.sched_getaffinity(spinner.pid) == {cpu}
    finally:
        spinner.terminate()
        spinner.wait(timeout=10)
    with pytest.raises(ValueError, match="CPU 10000 is not one this process may use"):
        loop.keep_awake(10_000)
    orphan = f"from mat_runtime import loop; print(loop.keep_awake({cpu}).pid)"
    pid = int(subprocess.run([sys.executable, "-c", orphan], capture_output=True,
                             text=True, check=True).stdout)  # fmt: skip
    deadline = time.monotonic() + 10
    while _alive(pid) and time.monotonic() < deadline:  # it ends with its parent
        time.sleep(0.05)
    assert not _alive(pid)


def _alive(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().split(") ")[1][0] != "Z"  # a zombie has ended
    except FileNotFoundError:
        return False


@pytest.mark.slow
def test_bench_jitter_prints_idle_and_loaded_tables():
    out = subprocess.run(
        ["mat", "bench", "jitter", "--seconds", "0.3"], capture_output=True, text=True, check=True
    ).stdout
    assert "### idle machine" in out and "busy processes competing" in out, out
    assert out.count("| cheetah-6x1 (n = 6) | 1000 Hz |") == 2, out
    assert out.count("| swimmer-65 (n = 64) | 100 Hz |") == 2, out
    assert "| act(obs, out=...) |" in out, out
    assert "| act(obs, out=...), 20,000 calls |" in out, out  # call by call: the floor
    assert "### the core's own stalls" in out and "gaps > 1000 µs" in out, out


def test_a_bundle_remembers_its_robot_and_the_controller_runs_on_it(tmp_path):
    """Faults and env options reach the manifest; the example drives that robot by default."""
    changed = {"faults": {"agent_1": "remove"}, "env_options": {"episode_limit": 40}}
    ckpt = make_checkpoint(tmp_path / "c.pt", "hopper-4x1", "mat", **changed)
    export(ckpt, tmp_path / "bundle", agent_counts=(3,))
    policy = Policy.load(tmp_path / "bundle")
    assert (policy.env_id, policy.env_faults, policy.env_options) == (
        "hopper-4x1",
        changed["faults"],
        changed["env_options"],
    )
    out = _run_example("controller.py", str(tmp_path / "bundle"), "--seconds", "0.5")
    assert "with agents ['agent_0', 'agent_2', 'agent_3']" in out, out
    assert "episode returns: none finished" not in out  # 50 steps at 100 Hz, 40-step episodes


def test_one_controller_serves_a_robot_whose_count_changes_between_episodes(tmp_path):
    options = {"agent_id": False, "episode_limit": 30}
    ckpt = make_checkpoint(tmp_path / "c.pt", "swimmer-4", "mat", env_options=options)
    export(ckpt, tmp_path / "bundle", agent_counts=(3,))
    out = _run_example("variable_agents.py", str(tmp_path / "bundle"), "--sizes", "3", "7", "5")
    for row in ("| 0 | swimmer-3 | 2 |", "| 1 | swimmer-7 | 6 |", "| 2 | swimmer-5 | 4 |"):
        assert row in out, out


def test_runtime_works_where_torch_cannot_be_imported(bundles):
    bundle = bundles["mat"][1]
    script = f"""
import sys
sys.modules["torch"] = None  # any `import torch` now raises ImportError
import numpy as np
from mat_runtime import Policy
policy = Policy.load({str(bundle)!r})
actions = policy.act(np.zeros((5, policy.obs_dim)))
assert actions.shape == (5, policy.action_size), actions.shape
banned = ("torch", "mat_sdk", "mat_export")
loaded = sorted(m for m, mod in sys.modules.items() if mod and m.split(".")[0] in banned)
assert not loaded, loaded
print("ok")
"""
    result = subprocess.run(
        [sys.executable, "-c", script], capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0 and result.stdout.strip() == "ok", result.stderr


def test_runtime_imports_only_numpy_and_onnxruntime():
    import ast
    from pathlib import Path

    allowed = {"numpy", "onnxruntime", "mat_runtime", "__future__"}
    # a robot's middleware, in the module that speaks it, which nothing else imports
    optional = {"unitree.py": {"cyclonedds"}}
    stdlib = set(sys.stdlib_module_names)
    for path in Path(mat_runtime.__file__).parent.glob("*.py"):
        if path.name != "unitree.py":
            assert "unitree" not in path.read_text(), f"{path.name} names the unitree module"
        for node in ast.walk(ast.parse(path.read_text())):
            names = []
            if isinstance(node, ast.Import):
                names = [alias.name for alias in node.names]
            elif isinstance(node, ast.ImportFrom) and node.module:
                names = [node.module]
            for name in names:
                top = name.split(".")[0]
                mine = allowed | optional.get(path.name, set())
                assert top in mine or top in stdlib, f"{path.name} imports {name}"


def _rehash(directory, name):
    import hashlib

    return hashlib.sha256((directory / name).read_bytes()).hexdigest()


def test_graph_paths_must_stay_inside_the_bundle(bundles, tmp_path):
    import shutil

    outside = tmp_path / "outside.onnx"
    outside.write_bytes(b"secret")
    bundle = tmp_path / "traversal"
    shutil.copytree(bundles["mat"][1], bundle)
    manifest = json.loads((bundle / "manifest.json").read_text())
    sneaky = "decode_n2/../../outside.onnx"
    manifest["graphs"][sneaky] = {**manifest["graphs"]["decode_n2.onnx"], "sha256": "0" * 64}
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match=r"graphs\.decode_n2/\.\./\.\./outside\.onnx is not a"):
        Policy.load(bundle)

    linked = tmp_path / "linked"
    shutil.copytree(bundles["mat"][1], linked)
    (linked / "decode_n2.onnx").unlink()
    (linked / "decode_n2.onnx").symlink_to(outside)
    manifest = json.loads((linked / "manifest.json").read_text())
    manifest["graphs"]["decode_n2.onnx"]["sha256"] = _rehash(linked, "decode_n2.onnx")
    (linked / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(BundleError, match="resolves outside the bundle directory"):
        Policy.load(linked)


def _damaged(source, target, edit):
    import shutil

    shutil.copytree(source, target)
    manifest = json.loads((target / "manifest.json").read_text())
    edit(manifest, target)
    (target / "manifest.json").write_text(json.dumps(manifest))
    return target


def test_manifests_that_lie_are_refused_naming_the_field(bundles, tmp_path):
    def set_field(*path_and_value):
        *path, value = path_and_value

        def edit(manifest, _):
            *parents, last = path
            node = manifest
            for key in parents:
                node = node[key]
            if value is KeyError:
                del node[last]
            else:
                node[last] = value

        return edit

    def truncate(manifest, directory):
        graph = directory / "decode.onnx"
        graph.write_bytes(graph.read_bytes()[:500])
        manifest["graphs"]["decode.onnx"]["sha256"] = _rehash(directory, "decode.onnx")

    def relabel(manifest, directory):  # decode_n2's graph listed as the 3-agent one
        (directory / "decode_n2.onnx").rename(directory / "decode_n3.onnx")
        manifest["graphs"]["decode_n3.onnx"] = {
            **manifest["graphs"].pop("decode_n2.onnx"),
            "agents": 3,
        }

    def edit_column(**fields):
        def edit(manifest, _):
            manifest["wiring"]["agents"][0]["action"][0].update(fields)

        return edit

    cases = {
        "obs_dim": (set_field("obs_dim", -17), r"obs_dim must be an integer in 1\.\."),
        "huge": (set_field("obs_dim", 10**30), r"obs_dim must be an integer in 1\.\."),
        "size": (set_field("action", "size", 5), r"action is .*'size': 5.*exported with action"),
        "type": (set_field("action", "type", 3), r"action\.type must be one of"),
        "low": (set_field("action", "low", "x"), r"action\.low must be a finite number"),
        "bounds": (set_field("action", "low", 2.0), r"action\.low must be below action\.high"),
        "algo": (set_field("algo", KeyError), "algo is missing"),
        "other algo": (
            set_field("algo", "mat-dec"),
            r"algo is 'mat-dec', but decode.onnx was exported with algo 'mat'",
        ),
        "no agents": (set_field("agents", KeyError), "agents is missing"),
        "float version": (set_field("version", 1.0), "bundle format version 1.0"),
        "true version": (set_field("version", True), "bundle format version True"),
        "agents": (set_field("agents", [1]), "agents must be an object"),
        "max": (set_field("agents", "max", 0), r"agents\.max must be an integer"),
        "entry": (set_field("graphs", "decode.onnx", "x"), r"graphs\.decode\.onnx must be an"),
        "count": (
            set_field("graphs", "decode_n2.onnx", "agents", 5),
            r"decode_n2\.onnx\.agents must be 2",
        ),
        "relabelled": (relabel, r"decode_n3\.onnx: .*has shape \['batch', 2"),
        "truncated": (truncate, "cannot load this graph"),
        "timestep": (
            set_field("wiring", "control_timestep", -1), r"wiring\.control_timestep must be in"
        ),
        "huge timestep": (
            set_field("wiring", "control_timestep", 1e300), r"wiring\.control_timestep must be in"
        ),
        "tiny timestep": (
            set_field("wiring", "control_timestep", 1e-300), r"wiring\.control_timestep must be in"
        ),
        "physics timestep": (
            set_field("wiring", "physics_timestep", "fast"),
            r"wiring\.physics_timestep must be a finite number",
        ),
        "physics slower than control": (
            set_field("wiring", "physics_timestep", 1.0), r"wiring\.physics_timestep must be in"
        ),
        "ctrl": (
            set_field("wiring", "agents", 0, "action", 0, "ctrl", 10**9),
            r"wiring\.agents\[0\]\.action\[0\]\.ctrl must be below",
        ),
        "low above high": (
            edit_column(low=1.0, high=-1.0), r"action\[0\] has low 1.0 > high -1.0"
        ),
        "kp without target": (edit_column(kp=5.0, kd=0.1), r"action\[0\]\.target must be a string"),
        "kp alone": (edit_column(kp=5.0), r"action\[0\]\.kd must be a finite number"),
        "negative kp": (
            edit_column(kp=-5.0, kd=0.1, target="thigh", torque=[-1, 1]),
            r"action\[0\]\.kp must be >= 0",
        ),
        "torque": (
            edit_column(kp=5.0, kd=0.1, target="thigh", torque=[1, -1]),
            r"action\[0\]\.torque must have low <= high",
        ),
        "signals": (
            set_field("wiring", "observation", "signals", 5),
            r"wiring\.observation\.signals must map signal names",
        ),
        "columns": (
            set_field("wiring", "agents", 0, "action", []), r"wiring\.agents\[0\]\.action must list"
        ),
        "index": (
            set_field("wiring", "observation", "index", 0, 0, 10**6),
            r"wiring\.observation\.index must hold integers in 0\.\.",
        ),
        "source": (
            set_field("wiring", "observation", "source", "qvel", [1, 2]),
            r"wiring\.observation\.source\.qvel must be \[",
        ),
    }  # fmt: skip
    for case, (edit, message) in cases.items():
        target = _damaged(bundles["mat"][1], tmp_path / case, edit)
        with pytest.raises(BundleError, match=message):
            Policy.load(target)
    deep = _damaged(bundles["mat"][1], tmp_path / "deep", lambda m, d: None)
    (deep / "manifest.json").write_text("[" * 100_000 + "]" * 100_000)
    with pytest.raises(BundleError, match="manifest.json"):
        Policy.load(deep)


@pytest.mark.parametrize(
    ("env_id", "options"),
    [
        pytest.param(
            "cheetah-6x1",
            {"faults": {"agent_1": "remove", "ffoot": "zero"}},
            marks=pytest.mark.slow,
        ),
        pytest.param("swimmer-5", {"env_options": {"position": "ends"}}, marks=pytest.mark.slow),
        ("my_robots:arm", {}),  # position servos: ctrl ranges that are not [-1, 1]
    ],
)
def test_the_bundles_wiring_rebuilds_observations_and_commands_from_raw_state(
    tmp_path, env_id, options
):
    """A controller with the bundle alone: observations gathered from qpos / qvel / task
    features equal the env's own, and the commands equal the ctrl the env writes."""
    with_examples()
    ckpt = make_checkpoint(tmp_path / "c.pt", env_id, "mat", **options)
    export(Trusted(ckpt), tmp_path / "bundle", agent_counts=(1,))  # our own arm
    policy = Policy.load(tmp_path / "bundle")
    team = make_team(env_id, faults=options.get("faults"), **options.get("env_options", {}))
    wiring, data = policy.wiring, team.physics.data
    assert [a.name for a in wiring.agents] == team.agents
    assert wiring.control_timestep == team.control_timestep
    rng = np.random.default_rng(0)
    obs = team.reset(seed=0)
    for _ in range(30):
        np.testing.assert_array_equal(
            wiring.observe(data.qpos, data.qvel, team.task_features()), obs
        )
        actions = rng.uniform(-1.5, 1.5, (team.n_agents, team.action_width))
        obs, *_ = team.step(actions)
        index, values = wiring.commands(actions)
        np.testing.assert_allclose(data.ctrl[index], values, rtol=1e-12, atol=1e-12)
    described = policy.describe()
    assert "control timestep" in described and "observation (every agent): joints.qpos" in described
    if "faults" in options:  # a removed agent is not wired; a zeroed actuator drives nothing
        assert "agent_1" not in described and "ffoot, " not in described
        assert [c.ctrl for c in wiring.agents[-1].action] == [None]


@pytest.mark.parametrize(
    "env_id",
    [
        "cheetah-6x1",  # torque actuators driven directly
        "my_robots:arm",  # position servos: their gains and the joints' ranges
        "go2:walk_torque",  # torque motors behind a PD layer, hardware signals, commands
        "mamujoco:Ant-4x2",  # no observation layout: Gymnasium builds the observations
    ],
)
def test_the_wiring_an_env_writes_is_the_wiring_the_runtime_reads(env_id):
    """One schema for both sides: what an env describes survives the manifest's JSON exactly."""
    with_examples()
    team = make_team(env_id)
    written = team.wiring().placed("inside the graphs")
    text = json.dumps(written.to_json())
    read = WiringSpec.from_json(json.loads(text), team.obs_dim, team.action_width, "manifest")
    assert read == written
    assert json.dumps(read.to_json()) == text


def test_a_bundle_without_wiring_still_loads_and_says_so(bundles, tmp_path):
    older = _damaged(bundles["mat"][1], tmp_path / "older", lambda m, d: m.pop("wiring"))
    policy = Policy.load(older)
    assert policy.wiring is None and "no wiring in this bundle" in policy.describe()
    assert policy.act(_obs(policy, 2)).shape == (2, policy.action_size)
    game = Policy.load(bundles["mat-discrete"][1])  # a game: nothing to wire
    assert game.wiring is None


def test_an_onnxruntime_too_old_for_the_opset_is_named(bundles, monkeypatch):
    import mat_runtime.policy as runtime_policy

    monkeypatch.setattr(runtime_policy.ort, "__version__", "1.23.2")
    with pytest.raises(BundleError, match=r"opset 24, which needs onnxruntime >= 1\.24\.1"):
        Policy.load(bundles["mat"][1])


def test_a_negative_seed_is_an_input_error(bundles):
    policy = Policy.load(bundles["mat"][1])
    with pytest.raises(InputError, match="seed must be an int >= 0, got -1"):
        policy.act(_obs(policy, 2), deterministic=False, seed=-1)
    assert policy.act(_obs(policy, 2)).shape == (2, policy.action_size)  # still serving


def test_the_wiring_refuses_malformed_readings_and_actions(bundles):
    """What a controller hands the wiring is checked: a command is never made from NaN
    actions or an array of another shape, nor an observation from complex or NaN readings."""
    policy = Policy.load(bundles["mat"][1])
    wiring = policy.wiring
    team = make_team("hopper-2x2", seed=0)
    data = team.physics.data
    actions = np.zeros((len(wiring.agents), policy.action_size))
    index, values = wiring.commands(actions)
    assert np.isfinite(values).all() and len(index) == len(values)
    with pytest.raises(ValueError, match="NaN or infinite"):
        wiring.commands(np.full_like(actions, np.nan))
    for shape in [(6, 3), (4, 3, 1), (len(wiring.agents),)]:
        with pytest.raises(ValueError, match=r"actions must have shape \[agents, width\]"):
            wiring.commands(np.zeros(shape))
    with pytest.raises(ValueError, match="actions must be real numbers"):
        wiring.commands(actions.astype(complex))
    qpos, qvel = data.qpos.copy(), data.qvel.copy()
    assert wiring.observe(qpos, qvel, team.task_features()).shape[0] == len(wiring.agents)
    with pytest.raises(ValueError, match="qpos must be real numbers"):
        wiring.observe(qpos.astype(complex), qvel, team.task_features())
    qpos[1] = np.nan
    with pytest.raises(ValueError, match="signal qpos holds NaN"):
        wiring.observe(qpos, qvel, team.task_features())
