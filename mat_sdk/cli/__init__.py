"""The `mat` command line: one small module per command, each turning its options into
library arguments and making one library call. Heavy imports happen inside commands, so
`--help` stays instant."""

from __future__ import annotations

import os
import sys

import click


@click.group(context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="mat-sdk")
def main() -> None:
    """MAT SDK: train Multi-Agent Transformer policies on multi-agent MuJoCo robots (ours
    or yours) and PettingZoo envs, export them to ONNX, and run them without torch.

    \b
    Start here:
      mat envs                          the robots and their agent decompositions
      mat rollout cheetah-6x1           a random team, to see an env work
      mat train cheetah-6x1 --steps 200000 --out runs/cheetah
      mat train cheetah-6x1 --seeds 5 --steps 2000000 --out runs/c5   then: mat report runs/c5
      mat eval runs/cheetah/checkpoint.pt --episodes 5 --fault bfoot=zero
      mat export runs/cheetah/checkpoint.pt -o cheetah_onnx   then: mat_runtime.Policy
      mat finetune runs/cheetah/checkpoint.pt --fault bthigh=zero --steps 20000
      mat bench envs                    env stepping speed (also: runtime, jitter, train, scaling)
      mat zoo                           trained models that ship with the project (zoo:NAME)

    \b
    Your own robot or PettingZoo env: docs/CUSTOM_ENVS.md; a real robot from a
    MuJoCo Menagerie model to a controller on its own sensors: docs/REAL_ROBOTS.md.
    """
    # module:function env ids import from the current directory, as `python -m` would
    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())


from mat_sdk.cli import (  # noqa: E402  (each module adds its commands to `main`)
    bench,
    envs,
    evaluate,
    export,
    finetune,
    report,
    train,
    zoo,
)

__all__ = ["bench", "envs", "evaluate", "export", "finetune", "main", "report", "train", "zoo"]
