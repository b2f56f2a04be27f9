"""`mat eval`: a trained policy's episodes, on its robot or a changed one."""

from __future__ import annotations

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import fault_option, parse_settings, trust_option, user_errors


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
@click.option(
    "--sweep", metavar="FACTOR=VALUES",
    help="Evaluate at each value of one randomization factor, the rest nominal: "
    "VALUES is low:high:count or a list, e.g. friction=0.4:1.2:5, payload=0,1,2, latency=0,1,2.",
)  # fmt: skip
@click.option(
    "--grid", is_flag=True,
    help="A legged robot's tracking report: --episodes at each command of a joystick's grid "
    "(vx, vy, yaw rate alone, standing, combined); per command the velocity measured in the "
    "heading frame, the error, falls.",
)  # fmt: skip
@click.option(
    "--grid-command", "grid_commands", multiple=True, metavar="VX,VY,YAW",
    help="With --grid: hold this command (m/s, m/s, rad/s) instead of the joystick grid's; "
    "repeat for more rows, e.g. --grid-command 0,0.2,0 --grid-command 0.2,0.2,0.",
)  # fmt: skip
@click.option(
    "--plot", type=click.Path(dir_okay=False),
    help="With --sweep or --grid: plot it to FILE.png.",
)  # fmt: skip
@trust_option()
@user_errors
def evaluate(
    checkpoint, episodes, env_id, faults, stochastic, video, seed, env_options, sweep, grid,
    grid_commands, plot,
) -> None:  # fmt: skip
    """Evaluate CHECKPOINT: mean +- std episode return (deterministic actions by default),
    episodes that ended early (a robot's fall), and a floating-base robot's forward speed.

    Robustness: `--env-option 'randomize=true'` evaluates under the default randomization
    (or a mapping of factors); `--sweep` holds one factor at each value in turn (a scale for
    friction, mass, strength, damping, armature; kg of payload; control steps of latency) and
    prints a table per value.

    \b
    Examples:
      mat eval runs/cheetah/checkpoint.pt --episodes 5 --fault bfoot=zero --video run.mp4
      mat eval runs/go2/checkpoint.pt --env-option 'command=[0.7,0,0]' --trust-env-code
      mat eval runs/go2/checkpoint.pt --sweep friction=0.4:1.2:5 --plot friction.png
      mat eval runs/go2/checkpoint.pt --grid --episodes 5 --plot tracking.png --trust-env-code
      mat eval runs/go2/checkpoint.pt --grid --grid-command 0,0.3,0 --grid-command 0.2,0.3,0 \\
          --episodes 2 --trust-env-code   # where does sideways walking start?
    """
    from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate_episodes

    loaded = CheckpointPolicy.from_checkpoint(checkpoint)
    if plot and not (sweep or grid):
        raise click.UsageError("--plot draws a sweep or a grid: give --sweep or --grid too")
    if sweep and grid:
        raise click.UsageError("--sweep and --grid are two reports: give one")
    if grid_commands and not grid:
        raise click.UsageError("--grid-command gives the rows of a --grid: give --grid too")
    options = parse_settings(env_options, param_hint="--env-option")
    if sweep or grid:
        given = {"--env": env_id, "--fault": faults, "--stochastic": stochastic, "--video": video}
        for name, value in given.items():
            if value:
                report = "--grid" if grid else "--sweep"
                raise click.UsageError(
                    f"{report} evaluates the checkpoint's own robot; drop {name}"
                )
        if grid:
            _grid(loaded, grid_commands, plot, episodes, seed, options)
        else:
            _sweep(loaded, sweep, plot, episodes, seed, options)
        return
    result = evaluate_episodes(
        loaded,
        episodes,
        env_id=env_id,
        deterministic=not stochastic,
        seed=seed,
        video=video,
        **({"faults": faults} if faults else {}),
        **options,
    )
    name = env_id or loaded.training.env.id
    click.echo(f"{name}: {result.summary()}")
    if result.terms:
        click.echo(result.breakdown())
    if video:
        click.echo(f"video: {video}")


def _sweep(loaded, sweep, plot, episodes, seed, options):
    from mat_sdk.evaluation import robustness

    factor, sep, values = sweep.partition("=")
    if not sep:
        raise click.BadParameter(f"{sweep!r}: use FACTOR=VALUES", param_hint="--sweep")
    points = robustness.sweep(
        loaded, factor, robustness.parse_values(values), episodes, seed, **options
    )
    click.echo(robustness.table(points, factor))
    if plot:
        click.echo(f"plot: {robustness.plot({'policy': [points]}, factor, plot)}")


def _grid(loaded, grid_commands, plot, episodes, seed, options):
    from mat_sdk.evaluation import tracking

    if "command" in options:
        raise click.UsageError("--grid sets the command itself, one per row; drop command=")
    try:
        commands = [tracking.parse_command(text) for text in grid_commands]
    except ValueError as error:
        raise click.BadParameter(str(error), param_hint="--grid-command") from None
    rows = tracking.track(loaded, commands or tracking.JOYSTICK_GRID, episodes, seed, **options)
    click.echo(tracking.table(rows))
    if plot:
        click.echo(f"plot: {tracking.plot(rows, plot)}")
