"""`mat finetune`: adapt a trained policy to a changed robot with little new data."""

from __future__ import annotations

from pathlib import Path

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import (
    fault_option,
    parse_settings,
    quiet_option,
    resumable,
    set_option,
    trust_option,
    user_errors,
)

FINETUNE_OPTIONS = {
    "env": "the ENV_ID argument",
    "more_envs": "the ENV_ID arguments after the first",
    "faults": "--fault NAME=zero|remove|weak:S",
    "lr": "--lr",
}


@main.command()
@click.argument("checkpoint", type=click.Path())
@click.argument("env_id", required=False)
@fault_option("The change to adapt to.")
@click.option("--steps", default=20_000, show_default=True, help="Fine-tuning env steps.")
@click.option(
    "--out", "out_dir", type=click.Path(file_okay=False), help="Run directory [runs/finetune-…]."
)
@click.option("--lr", type=float, help="Learning rate [the checkpoint's].")
@click.option(
    "--episodes", default=10, show_default=True, help="Evaluation episodes (before/after)."
)
@click.option("--keep-optimizer", is_flag=True, help="Keep the checkpoint's Adam moments.")
@click.option(
    "--action-std",
    type=float,
    help="Start from this action std, 0-0.5 (e.g. 0.3), to explore again for a new gait "
    "[the checkpoint's].",
)
@click.option("--resume", is_flag=True, help="Continue an interrupted fine-tuning run in OUT.")
@set_option()
@trust_option()
@quiet_option()
@user_errors
def finetune(
    checkpoint,
    env_id,
    faults,
    steps,
    out_dir,
    lr,
    episodes,
    keep_optimizer,
    action_std,
    resume,
    settings,
    quiet,
) -> None:
    """Adapt a trained CHECKPOINT to a changed robot (ENV_ID, default: the same env).

    \b
    Evaluates the pre-trained policy on the changed robot first (zero-shot), then runs PPO
    from its weights and normalisers, and evaluates again. OUT gets checkpoint.pt,
    metrics.csv, the curve and finetune.json (both evaluations).
    A removed agent ("remove") leaves its team-mates' one-hot ids as they were; swimmer-N
    has no ids, so swimmer-6 -> swimmer-9 works. Changes that alter the observation or
    action size are refused.

    \b
    Examples:
      mat finetune runs/cheetah/checkpoint.pt --fault bthigh=zero --steps 20000
      mat finetune runs/swimmer6/checkpoint.pt swimmer-9 --steps 50000 --out runs/sw9
      mat finetune runs/go2/checkpoint.pt --fault FR_calf_joint=weak:0.5 --steps 99200 \\
          --action-std 0.3 --trust-env-code   # a weak knee, a new gait: explore again
      mat finetune runs/go2/checkpoint.pt --steps 99200 --lr 1e-3 --trust-env-code \\
          --set 'env_options={"randomize": {"payload": [6.0, 6.0]}}'   # 6 kg on the trunk
    """
    import numpy as np

    from mat_sdk.training.finetune import default_out
    from mat_sdk.training.finetune import finetune as run

    out = Path(out_dir) if out_dir else default_out(env_id, faults)
    again = f"mat finetune {checkpoint} --out {out} --steps {steps} --resume"
    options = parse_settings(settings, FINETUNE_OPTIONS)
    with resumable(out / "checkpoint.pt", again):
        result = run(
            checkpoint,
            env=env_id,
            steps=steps,
            out_dir=out,
            eval_episodes=episodes,
            reset_optimizer=not keep_optimizer,
            lr=lr,
            action_std=action_std,
            resume=resume,
            progress_bar=not quiet,
            **({"faults": faults} if faults else {}),
            **options,
        )
    result.trainer.close()
    click.echo(
        f"zero-shot return {result.zero_shot_mean:.1f} ± {np.std(result.zero_shot):.1f} -> "
        f"after {result.trainer.progress.steps:,} steps {result.final_mean:.1f} ± "
        f"{np.std(result.final):.1f} ({episodes} episodes each)"
    )
    click.echo(f"checkpoint: {out / 'checkpoint.pt'}   summary: {out / 'finetune.json'}")
