"""Two checkouts of the SDK side by side: the runtime's control step and a training update,
measured in alternating fresh processes (interleaved rounds, medians).

    python -m benchmarks.before_after OLD_PACKAGES NEW_PACKAGES --rounds 5 [--act-only]

Each PACKAGES is a directory holding `mat_sdk`, `mat_runtime` and `mat_export` (symlinks to
a checkout's `mat_sdk/`, `runtime/` and `export/` will do). Both act with the same bundle
(`zoo:cheetah-6x1-mat`) and train the same run (`cheetah-6x1`, the paper's recipe, one
process); the table gives each one's medians and new / old.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
from pathlib import Path

ZOO = Path(__file__).resolve().parents[1] / "zoo"
MEASURE = r"""
import json, sys, time, numpy as np
from mat_runtime import Policy
policy = Policy.load("zoo:cheetah-6x1-mat", threads=1)
obs = np.random.default_rng(0).standard_normal((6, policy.obs_dim)).astype(np.float32)
for _ in range(500):
    policy.act(obs)
times = []
for _ in range(3000):
    start = time.perf_counter(); policy.act(obs); times.append(time.perf_counter() - start)
result = {"act_us": float(np.median(times)) * 1e6}
if sys.argv[1] == "train":
    try:
        from mat_sdk.training.trainer import Trainer
    except ImportError:  # a checkout from before the folders
        from mat_sdk.trainer import Trainer
    rows = []
    with Trainer("cheetah-6x1", "mat", num_envs=40, rollout_length=100) as trainer:
        trainer.learn(12_000, progress_bar=False, callback=lambda t, m: rows.append(m))
    result["update_s"] = float(np.median([r["update_s"] for r in rows[1:]]))
    result["steps_per_s"] = float(np.median([r["steps_per_s"] for r in rows[1:]]))
print(json.dumps(result))
"""


def measure(packages: Path, train: bool) -> dict:
    environment = {**os.environ, "PYTHONPATH": str(packages), "MAT_ZOO": str(ZOO)}
    command = [sys.executable, "-c", MEASURE, "train" if train else "act"]
    run = subprocess.run(command, env=environment, cwd="/", capture_output=True, text=True,
                         check=True)  # fmt: skip
    return json.loads(run.stdout.strip().splitlines()[-1])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("old", type=Path)
    parser.add_argument("new", type=Path)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--act-only", action="store_true", help="the control step alone")
    args = parser.parse_args()
    results: dict[str, list[dict]] = {"old": [], "new": []}
    for _ in range(args.rounds):
        for name in ("old", "new"):
            results[name].append(measure(getattr(args, name), not args.act_only))
    print("| measure | old | new | new / old |\n|---|---|---|---|")
    for key in results["new"][0]:
        old = statistics.median(r[key] for r in results["old"])
        new = statistics.median(r[key] for r in results["new"])
        print(f"| {key} | {old:,.4g} | {new:,.4g} | {new / old:.3f} |")


if __name__ == "__main__":
    main()
