"""`mat eval`: a trained policy's episodes, on its robot or a changed one."""

from __future__ import annotations

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import fault_option, parse_faults, parse_settings, trust_option, user_errors


@main.command("eval")
@click.argument("checkpoint", type=click.Path())
@click.option("--episodes", default=10, show_default=True)
@click.option("--env", "env_id", help="Another env the policy can serve [the checkpoint's].")
@fault_option("Break a joint or agent.")
@click.option(
    "--stochastic", is_flag=True, help="Sample actions instead of the deterministic mean/argmax."
)
@click.option(
    "--video", type=click.Path(dir_okay=False), help="Record the first episode to FILE.mp4."
)
@click.option("--seed", default=10_000, show_default=True)
@click.option(
    "--env-option", "env_options", multiple=True, metavar="KEY=VALUE",
    help="Change an env option for this evaluation (JSON value), e.g. command=[0.7,0,0].",
)  # fmt: skip
@trust_option()
@user_errors
def evaluate(
    checkpoint, episodes, env_id, faults, stochastic, video, seed, env_options, trust_env_code
) -> None:
    """Evaluate CHECKPOINT: mean +- std episode return (deterministic actions by default),
    episodes that ended early (a robot's fall), and a floating-base robot's forward speed.

    \b
    Examples:
      mat eval runs/cheetah/checkpoint.pt --episodes 5 --fault bfoot=zero --video run.mp4
      mat eval runs/go2/checkpoint.pt --env-option 'command=[0.7,0,0]' --trust-env-code
    """
    from mat_sdk.evaluation import CheckpointPolicy, evaluate_episodes

    loaded = CheckpointPolicy.from_checkpoint(checkpoint)
    result = evaluate_episodes(
        loaded,
        episodes,
        env_id=env_id,
        faults=parse_faults(faults) if faults else None,
        deterministic=not stochastic,
        seed=seed,
        video=video,
        trust_env_code=trust_env_code,
        **parse_settings(env_options, param_hint="--env-option"),
    )
    name = env_id or loaded.config["train"]["env"]
    click.echo(f"{name}: {result.summary()}")
    if video:
        click.echo(f"video: {video}")
