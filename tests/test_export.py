"""ONNX export: parity with torch, self-describing deterministic bundles, loud refusals."""

import hashlib
import json
import re

import numpy as np
import onnx
import pytest
import torch
from click.testing import CliRunner
from helpers import make_checkpoint

from mat_export import ExportError, export, exporter
from mat_export import parity as parity_module
from mat_sdk.cli import main
from mat_sdk.policy import checkpoint


@pytest.fixture(scope="module")
def mat_checkpoint(tmp_path_factory):
    return make_checkpoint(tmp_path_factory.mktemp("ckpt") / "mat.pt", n_block=2, n_head=2)


@pytest.fixture(scope="module")
def mat_bundle(mat_checkpoint, tmp_path_factory):
    """The checkpoint's bundle, exported once for the tests that only read it."""
    bundle = tmp_path_factory.mktemp("export") / "bundle"
    return bundle, export(mat_checkpoint, bundle)


def test_mat_bundle_matches_torch_and_describes_itself(mat_bundle):
    bundle, manifest = mat_bundle
    assert sorted(p.name for p in bundle.iterdir()) == [
        "decode.onnx",
        "decode_n2.onnx",  # unrolled for hopper-2x2's two agents
        "decoder_step.onnx",
        "encoder.onnx",
        "manifest.json",
    ]
    assert manifest["graphs"]["decode_n2.onnx"]["agents"] == 2
    diffs = manifest["parity"]["max_abs_diff"]
    assert list(diffs) == ["1", "2", "6", "17", "64"]
    assert max(diffs.values()) <= 1e-5
    on_disk = json.loads((bundle / "manifest.json").read_text())
    assert on_disk["format"] == "mat-onnx" and on_disk["kind"] == "autoregressive"
    assert on_disk["action"] == {
        "type": "continuous",
        "size": 2,
        "low": -1.0,
        "high": 1.0,
        "token_size": 2,
    }
    step = on_disk["graphs"]["decoder_step.onnx"]
    assert (
        "past_key_values.1.attn2.value" in step["inputs"]
        and "present.1.attn2.value" in step["outputs"]
    )
    for name, entry in on_disk["graphs"].items():
        assert hashlib.sha256((bundle / name).read_bytes()).hexdigest() == entry["sha256"]
        model = onnx.load(str(bundle / name))
        onnx.checker.check_model(model, full_check=True)
        assert {node.domain for node in model.graph.node} <= {"", "ai.onnx"}
        props = {p.key: json.loads(p.value) for p in model.metadata_props}
        assert props["obs_dim"] == on_disk["obs_dim"] and props["algo"] == "mat"


def test_torchlibs_registry_is_built_once_while_exporting_and_torch_is_left_as_it_was():
    from torch.onnx._internal.exporter._registration import ONNXRegistry

    with exporter.torchlib_registry_reused():
        first = ONNXRegistry.from_torchlib(opset_version=exporter.OPSET)
        assert ONNXRegistry.from_torchlib(opset_version=exporter.OPSET) is first
    assert ONNXRegistry.from_torchlib(opset_version=exporter.OPSET) is not first


@pytest.mark.slow
def test_export_is_deterministic_and_builds_torchlibs_registry_once(
    mat_checkpoint, mat_bundle, tmp_path
):
    before = exporter._torchlib_registry.cache_info()
    export(mat_checkpoint, tmp_path / "b")
    after = exporter._torchlib_registry.cache_info()
    # the bundle's two torch-exported graphs reuse the registry the fixture's export built
    assert (after.hits - before.hits, after.misses - before.misses) == (2, 0)
    for name in (
        "encoder.onnx",
        "decoder_step.onnx",
        "decode.onnx",
        "decode_n2.onnx",
        "manifest.json",
    ):
        assert (mat_bundle[0] / name).read_bytes() == (tmp_path / "b" / name).read_bytes(), name


@pytest.mark.parametrize(
    ("env_id", "algo", "kind", "counts"),
    [
        ("coordination-3", "mat", "autoregressive", ["1", "2", "3", "6", "17", "64"]),
        ("hopper-2x2", "mat", "autoregressive", ["1", "2", "6", "17", "64"]),  # one head
        ("hopper-2x2", "mat-dec", "decentralised", ["1", "2", "6", "17", "64"]),
        ("coordination-3", "mappo", "decentralised", ["3"]),
        ("coordination-3", "happo", "decentralised", ["3"]),  # an actor per agent
        ("hopper-2x2", "happo", "decentralised", ["2"]),  # and a std per agent
    ],
)
def test_one_head_discrete_and_baseline_policies_export(tmp_path, env_id, algo, kind, counts):
    manifest = export(make_checkpoint(tmp_path / "c.pt", env_id, algo), tmp_path / "bundle")
    assert manifest["kind"] == kind and list(manifest["parity"]["max_abs_diff"]) == counts
    assert max(manifest["parity"]["max_abs_diff"].values()) <= 1e-5
    if manifest["action"]["type"] == "discrete":
        assert "available" in manifest["graphs"]["decoder_step.onnx"]["inputs"]


@pytest.mark.parametrize(
    ("env_id", "model"),
    [
        ("hopper-2x2", {}),  # stream
        pytest.param("coordination-3", {"n_head": 2, "n_block": 2}, marks=pytest.mark.slow),
    ],  # per-head
)
def test_windowed_attention_exports_at_parity_beyond_its_window(tmp_path, env_id, model):
    checkpoint = make_checkpoint(tmp_path / "c.pt", env_id, attention_window=3, **model)
    manifest = export(checkpoint, tmp_path / "bundle")
    assert manifest["model"]["attention_window"] == 3
    diffs = manifest["parity"]["max_abs_diff"]
    assert {"17", "64"} <= set(diffs) and max(diffs.values()) <= 1e-5  # counts past 2 x 3


def test_disagreement_refuses_and_leaves_nothing(mat_checkpoint, tmp_path, monkeypatch):
    monkeypatch.setattr(parity_module, "PARITY_LIMIT", -1.0)
    with pytest.raises(ExportError, match="disagrees with torch"):
        export(mat_checkpoint, tmp_path / "bundle")
    assert list(tmp_path.iterdir()) == []


def test_bad_input_is_refused_and_nothing_is_overwritten(mat_checkpoint, tmp_path):
    existing = tmp_path / "existing"
    existing.mkdir()
    (existing / "keep.txt").write_text("mine")
    for force in (False, True):  # a wrong -o (a run directory, ".") is never deleted
        with pytest.raises(ExportError, match="is not a MAT bundle.*not replacing it"):
            export(mat_checkpoint, existing, force=force)
    assert (existing / "keep.txt").read_text() == "mine"
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint at"):
        export(tmp_path / "missing.pt", tmp_path / "out")
    junk = tmp_path / "junk.pt"
    junk.write_text("not torch")
    with pytest.raises(checkpoint.CheckpointError, match="is not a MAT checkpoint"):
        export(junk, tmp_path / "out")
    newer = tmp_path / "newer.pt"
    torch.save({"format": "mat-checkpoint", "version": 2}, newer)
    with pytest.raises(checkpoint.CheckpointError, match="newer than this SDK"):
        export(newer, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_force_replaces_only_a_bundle_of_its_own_files(mat_checkpoint, mat_bundle, tmp_path):
    import shutil
    import time

    bundle = tmp_path / "bundle"
    shutil.copytree(mat_bundle[0], bundle)  # as an export leaves it
    (bundle / "notes.txt").write_text("mine")
    with pytest.raises(ExportError, match=r"holds files that are not the bundle's \(notes.txt\)"):
        export(mat_checkpoint, bundle, force=True)
    assert (bundle / "notes.txt").read_text() == "mine" and (bundle / "decode.onnx").exists()
    manifest = json.loads((bundle / "manifest.json").read_text())
    manifest["graphs"]["notes.txt"] = manifest["graphs"]["decode.onnx"]  # a doctored listing
    (bundle / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(ExportError, match=r"holds files that are not the bundle's \(notes.txt\)"):
        export(mat_checkpoint, bundle, force=True)
    assert (bundle / "notes.txt").read_text() == "mine"

    run = tmp_path / "run"  # the checkpoint exported into its own directory's bundle
    shutil.copytree(mat_bundle[0], run)
    shutil.copy(mat_checkpoint, run / "checkpoint.pt")
    with pytest.raises(ExportError, match="holds the checkpoint being exported"):
        export(run / "checkpoint.pt", run, force=True)
    assert (run / "checkpoint.pt").exists()

    link = tmp_path / "link"
    link.symlink_to(bundle)
    start = time.monotonic()
    with pytest.raises(ExportError, match="is a symlink"):
        export(mat_checkpoint, link, force=True)
    assert time.monotonic() - start < 5  # refused before any work
    assert (bundle / "notes.txt").exists()

    not_a_directory = tmp_path / "file"
    not_a_directory.write_text("x")
    with pytest.raises(ExportError, match="cannot write the bundle"):
        export(mat_checkpoint, not_a_directory / "bundle")


def test_a_checkpoint_of_an_unknown_env_exports_nothing(mat_checkpoint, tmp_path):
    payload = checkpoint.load(mat_checkpoint)
    payload["config"]["train"]["env"]["id"] = "cheetah-9x9"
    strange = checkpoint.save_atomic(payload, tmp_path / "strange.pt")
    with pytest.raises(ExportError, match="trained on env 'cheetah-9x9', which cannot be made"):
        export(strange, tmp_path / "out")
    assert not (tmp_path / "out").exists()


def test_mat_export_command(mat_checkpoint, mat_bundle, tmp_path):
    import shutil

    out = tmp_path / "cli_bundle"
    shutil.copytree(mat_bundle[0], out)  # a bundle is there already
    again = CliRunner().invoke(main, ["export", str(mat_checkpoint), "-o", str(out)])
    assert (
        again.exit_code != 0 and "pass --force" in again.output and "Traceback" not in again.output
    )
    forced = CliRunner().invoke(main, ["export", str(mat_checkpoint), "-o", str(out), "--force"])
    assert forced.exit_code == 0, forced.output
    assert "max abs diff" in forced.output and (out / "manifest.json").exists()


def test_folded_normaliser_gives_values_in_return_units(mat_checkpoint, mat_bundle):
    import onnxruntime as ort

    payload = checkpoint.load(mat_checkpoint)
    obs = (
        np.random.default_rng(1)
        .normal(size=(1, 2, payload["config"]["env"]["obs_dim"]))
        .astype(np.float32)
    )
    session = ort.InferenceSession(str(mat_bundle[0] / "encoder.onnx"))
    _, values = session.run(None, {"obs": obs})
    from mat_sdk.evaluation.episodes import CheckpointPolicy
    from mat_sdk.policy.normalization import ValueNorm

    loaded = CheckpointPolicy.from_checkpoint(mat_checkpoint)
    value_norm = ValueNorm()
    value_norm.load_state_dict(payload["value_norm"])
    with torch.no_grad():
        expected = value_norm.denormalize(
            loaded.policy.values(torch.from_numpy(loaded.obs_norm.normalize(obs)))
        )
    np.testing.assert_allclose(values, expected.numpy(), atol=1e-5)


def test_decode_graph_runs_the_whole_control_step_and_samples_from_given_noise(
    mat_checkpoint, mat_bundle
):
    import onnxruntime as ort

    from mat_sdk.evaluation.episodes import CheckpointPolicy

    session = ort.InferenceSession(str(mat_bundle[0] / "decode.onnx"))
    assert [i.name for i in session.get_inputs()] == ["obs", "noise"]
    names = ["actions", "clipped_actions", "mean", "std", "values", "obs_check"]
    assert [o.name for o in session.get_outputs()] == names
    loaded = CheckpointPolicy.from_checkpoint(mat_checkpoint)
    rng = np.random.default_rng(3)
    for n in (1, 5, 33):  # any agent count, one call
        obs = rng.normal(size=(2, n, loaded.policy.cfg.obs_dim)).astype(np.float32)
        zero = np.zeros((2, n, 2), np.float32)
        actions, _, mean, _, _, obs_check = session.run(None, {"obs": obs, "noise": zero})
        np.testing.assert_allclose(actions, mean)
        np.testing.assert_allclose(actions, loaded.act(obs), atol=1e-5)  # zero noise = the mean
        np.testing.assert_allclose(obs_check, obs.sum(dtype=np.float64), atol=1e-3)
        noise = 3 * rng.normal(size=(2, n, 2)).astype(np.float32)  # wide: some exceed [-1, 1]
        out = dict(zip(names, session.run(None, {"obs": obs, "noise": noise}), strict=True))
        sampled = out["actions"]
        np.testing.assert_allclose(sampled, out["mean"] + out["std"] * noise, atol=1e-6)
        assert not np.allclose(sampled, actions)
        assert (np.abs(sampled) > 1).any()
        np.testing.assert_array_equal(out["clipped_actions"], np.clip(sampled, -1, 1))
        for bad in (np.nan, np.inf, -np.inf):
            broken = obs.copy()
            broken[1, n - 1, 0] = bad
            obs_check = session.run(["obs_check"], {"obs": broken, "noise": zero})[0]
            assert not np.isfinite(obs_check)


@pytest.mark.parametrize(
    ("env_id", "model"),
    [
        ("hopper-2x2", {"n_block": 2, "n_head": 2}),  # per-head caches, continuous
        ("hopper-2x2", {}),  # one head: the streamed cache
        ("coordination-3", {}),  # discrete, with choices masked
    ],
)
def test_every_graph_runs_in_onnxs_reference_evaluator_at_parity(tmp_path, env_id, model):
    """A bundle is ONNX that engines other than ONNX Runtime run alike: the full checker
    passes and ONNX's own reference evaluator gives ORT's outputs for every graph, the
    any-count `decode.onnx` included, at agent counts its loops run 0, 1 and 2 times."""
    import onnxruntime as ort
    from onnx.reference import ReferenceEvaluator

    bundle = tmp_path / "bundle"
    export(make_checkpoint(tmp_path / "c.pt", env_id, "mat", **model), bundle)
    rng = np.random.default_rng(0)
    for path in sorted(bundle.glob("*.onnx")):
        onnx.checker.check_model(onnx.load(path), full_check=True)
        session, reference = ort.InferenceSession(path), ReferenceEvaluator(str(path))
        for agents in (1, 3, 9, 17):
            dims = {"batch": 2, "agents": agents, "past": 2}
            feeds = {}
            for spec in session.get_inputs():
                shape = [dims[d] if isinstance(d, str) else d for d in spec.shape]
                if "float" in spec.type:
                    feeds[spec.name] = rng.standard_normal(shape).astype(np.float32)
                else:  # which choices are available: all
                    feeds[spec.name] = np.ones(
                        shape, dtype=bool if "bool" in spec.type else np.float32
                    )
            if "agents" not in str([s.shape for s in session.get_inputs()]) and agents > 1:
                break  # a graph of one agent count, or one agent step
            want = session.run(None, feeds)
            got = reference.run(None, feeds)
            for name, a, b in zip([o.name for o in session.get_outputs()], want, got, strict=True):
                assert a.shape == b.shape, (path.name, agents, name)
                assert np.abs(a - b).max() <= 1e-4, (path.name, agents, name)


def test_openvino_runs_every_graph_of_the_bundle_at_parity_with_ort(tmp_path):
    """A second engine (OpenVINO, CPU, f32), as `mat export` checks it when installed: every
    graph at every count the export measures (1, 2, 6, 17 and 64 agents: `decode.onnx`'s
    bodies' loop runs zero, one, two and eight times, skipped by its `If` at zero), none
    refused, none wrong (compiled without the CPU plugin's runtime cache, which computed 32
    and 64 agents wrong on an AVX2 CPU)."""
    pytest.importorskip("openvino")
    checkpoint = make_checkpoint(tmp_path / "c.pt", "hopper-2x2", "mat")
    manifest = export(checkpoint, tmp_path / "bundle", engines=("openvino",))
    second = manifest["parity"]["openvino"]
    n = manifest["agents"]["trained"]
    graphs = {"encoder.onnx", "decoder_step.onnx", "decode.onnx", f"decode_n{n}.onnx"}
    assert graphs == set(second["max_abs_diff"]), second
    assert second["refused"] == {} and second["wrong"] == {}, second
    assert max(second["max_abs_diff"].values()) <= 1e-4
    assert second["config"]["CPU_RUNTIME_CACHE_CAPACITY"] == "0"  # how a robot should compile


def test_mat_export_reports_the_second_engine_and_refuses_an_unknown_one(tmp_path):
    """The command line, on a discrete policy (its choices' mask an input of every graph)."""
    from click.testing import CliRunner

    from mat_sdk.cli import main

    pytest.importorskip("openvino")
    checkpoint = make_checkpoint(tmp_path / "c.pt", "coordination-3", "mat")
    run = CliRunner().invoke(
        main, ["export", str(checkpoint), "-o", str(tmp_path / "b"), "--engine", "openvino"]
    )
    assert run.exit_code == 0, run.output
    assert re.search(r"openvino [\d.]+ \(CPU, f32\) vs ORT max abs diff: decode\.onnx", run.output)
    with pytest.raises(ValueError, match=r"engines: \['tensorrt'\] unknown; valid: openvino"):
        export(checkpoint, tmp_path / "c", engines=("tensorrt",))
