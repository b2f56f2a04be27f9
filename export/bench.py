"""One control step through ONNX Runtime: `decode.onnx` (one call) vs the step graph per agent.

B = 1, one thread, zero noise (the deterministic action), interleaved rounds, medians.
"""

from __future__ import annotations

import tempfile
from pathlib import Path

import numpy as np
from mat_export.exporter import decode_with_ort, export

from mat_sdk.bench import compare, print_table
from mat_sdk.trainer import Trainer

SIZES = {
    "1 block, 1 head": {"n_block": 1, "n_head": 1},
    "3 blocks, 4 heads": {"n_block": 3, "n_head": 4},
}


def _bundle(directory: Path, **model) -> tuple[Path, object]:
    with Trainer("cheetah-6x1", "mat", num_envs=1, rollout_length=1, **model) as trainer:
        path = trainer.save(directory / "model.pt")
        policy = trainer.policy
    export(path, directory / "bundle", agent_counts=(1, 2))
    return directory / "bundle", policy


def _variants(encoder, step, decode, policy, obs: np.ndarray) -> dict:
    """The two ways to run one control step, as zero-argument callables."""
    noise = np.zeros((*obs.shape[:2], policy.cfg.action_dim), np.float32)
    feed = {"obs": obs, "noise": noise}

    def stepwise():
        rep, _ = encoder.run(None, {"obs": obs})
        return decode_with_ort(policy, step, rep, None)

    return {"decode": lambda: decode.run(None, feed), "step": stepwise}


def main(agent_counts=(2, 6, 17, 64), seconds: float = 1.0) -> None:
    import onnxruntime as ort

    options = ort.SessionOptions()
    options.intra_op_num_threads = 1
    options.inter_op_num_threads = 1
    rows = []
    for label, model in SIZES.items():
        with tempfile.TemporaryDirectory() as tmp:
            bundle, policy = _bundle(Path(tmp), **model)
            encoder = ort.InferenceSession(str(bundle / "encoder.onnx"), options)
            step = ort.InferenceSession(str(bundle / "decoder_step.onnx"), options)
            decode = ort.InferenceSession(str(bundle / "decode.onnx"), options)
            for n in agent_counts:
                obs = (
                    np.random.default_rng(0)
                    .standard_normal((1, n, policy.cfg.obs_dim))
                    .astype(np.float32)
                )

                times = compare(_variants(encoder, step, decode, policy, obs), seconds)
                rows.append(
                    {
                        "model": label,
                        "agents": n,
                        "decode.onnx, one call (µs)": f"{times['decode'] * 1e6:,.0f}",
                        "step graph per agent from Python (µs)": f"{times['step'] * 1e6:,.0f}",
                        "speed-up": f"{times['step'] / times['decode']:.2f}x",
                    }
                )
    print_table(rows, "One control step through ONNX Runtime (B=1, 1 thread, median)")
