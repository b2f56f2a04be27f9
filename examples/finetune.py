"""Few-shot fine-tuning, the whole workflow: a trained cheetah loses a joint; adapt, export,
and run the adapted policy with the runtime.

    mat train cheetah-6x1 --steps 200000 --out runs/cheetah       # or any MAT checkpoint
    python examples/finetune.py runs/cheetah/checkpoint.pt --fault bthigh=zero --steps 20000
"""

from __future__ import annotations

import argparse
from pathlib import Path

from mat_export import export
from mat_runtime import Policy
from mat_sdk.envs import make_team
from mat_sdk.envs.core.faults import Fault
from mat_sdk.training.finetune import finetune


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("checkpoint", help="a checkpoint trained on the intact robot")
    parser.add_argument("--fault", default="bthigh=zero", metavar="NAME=zero|remove|weak:S")
    parser.add_argument("--steps", type=int, default=20_000, help="fine-tuning env steps")
    parser.add_argument("--out", type=Path, default=Path("runs/finetune-example"))
    args = parser.parse_args()
    fault = Fault.parse(args.fault)

    # 1. Zero-shot evaluation on the changed robot, then PPO from the pre-trained weights.
    result = finetune(args.checkpoint, faults=[fault], steps=args.steps, out_dir=args.out)
    result.trainer.close()
    print(f"zero-shot {result.zero_shot_mean:.1f} -> fine-tuned {result.final_mean:.1f}")

    # 2. Export the adapted policy (checked against torch) and act with the runtime only.
    bundle = export(args.out / "checkpoint.pt", args.out / "onnx", force=True)
    policy = Policy.load(args.out / "onnx")
    team = make_team(
        policy.env_id, faults=policy.env_faults, **policy.env_options
    )  # the changed robot
    obs, total, done = team.reset(seed=0), 0.0, False
    while not done:
        obs, reward, terminated, truncated = team.step(policy.act(obs))
        total += reward
        done = terminated or truncated
    print(f"runtime episode on the changed robot: return {total:.1f}")
    worst = max(bundle["parity"]["max_abs_diff"].values())
    print(f"bundle: {args.out / 'onnx'} (ONNX Runtime vs torch, max abs diff {worst:.1e})")


if __name__ == "__main__":
    main()
