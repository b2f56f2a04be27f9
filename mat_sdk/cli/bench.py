"""`mat bench ...`: benchmarks that print Markdown tables (BENCHMARKS.md)."""

from __future__ import annotations

import click

from mat_sdk.cli import main
from mat_sdk.cli.common import parse_counts, parse_settings, set_option, user_errors


@main.group()
def bench() -> None:
    """Benchmarks that print Markdown tables (paste them into BENCHMARKS.md)."""


@bench.command("envs")
@click.option("--seconds", default=1.0, show_default=True, help="Time per measured variant.")
@click.option(
    "--randomized",
    "robots",
    multiple=True,
    metavar="ENV",
    help="A robot for the randomization table (repeatable) [cheetah-6x1, quadruped-4x3, "
    "mamujoco:Ant-4x2]; e.g. PYTHONPATH=examples ... --randomized go2:walk.",
)
@user_errors
def bench_envs(seconds: float, robots: tuple[str, ...]) -> None:
    """Our env step vs dm_control's bare physics step, randomization's cost, vectorised rates."""
    from mat_sdk.bench.envs import RANDOMIZED
    from mat_sdk.bench.envs import main as run

    run(seconds=seconds, robots=robots or RANDOMIZED)


@bench.command("runtime")
@click.option("--seconds", default=2.0, show_default=True, help="Time per table row.")
@click.option(
    "--agents", default="2,6,17,64,256", show_default=True, help="Comma-separated agent counts."
)
@click.option(
    "--no-scaling",
    is_flag=True,
    help="Leave out the runtime alone at n = 64, 256, 1024 (time ratios, memory added).",
)
@user_errors
def bench_runtime(seconds: float, agents: str, no_scaling: bool) -> None:
    """One control step: mat_runtime vs the official re-decode, torch cached, step graph.

    \b
    Example:
      mat bench runtime --agents 6,64 --seconds 1 --no-scaling
    """
    from mat_sdk.bench.runtime import main as run

    run(agent_counts=parse_counts(agents, "--agents"), seconds=seconds, scale=not no_scaling)


@bench.command("jitter")
@click.option("--seconds", default=10.0, show_default=True, help="Measured time per row.")
@click.option("--cpu", type=int, help="Pin the loop to this core.")
@click.option("--fifo", type=int, metavar="PRIORITY", help="SCHED_FIFO at this priority (1-99).")
@click.option("--spin", is_flag=True, help="Busy-wait between ticks instead of sleeping.")
@click.option(
    "--keep-awake",
    is_flag=True,
    help="Spin a SCHED_IDLE process on the --cpu core so it never idles between ticks.",
)
@user_errors
def bench_jitter(
    seconds: float, cpu: int | None, fifo: int | None, spin: bool, keep_awake: bool
) -> None:
    """The control loop's p50 / p99 / p99.9 / max and late ticks, idle and under a CPU load.

    n = 6 at 1 kHz and n = 64 at 100 Hz (simulated robots, paper-size untrained policies),
    then again while one busy process per core competes (started and stopped here).

    \b
    Example:
      mat bench jitter --seconds 60 --cpu 1 --fifo 80 --keep-awake
    """
    from mat_sdk.bench.jitter import main as run

    if keep_awake and cpu is None:
        raise click.UsageError("--keep-awake keeps the loop's core awake: give it with --cpu")
    run(seconds=seconds, cpu=cpu, fifo=fifo, spin=spin, keep_awake=keep_awake)


@bench.command("scaling")
@click.option("--env", "env_id", default="cheetah-6x1", show_default=True)
@click.option("--updates", default=3, show_default=True, help="Updates per variant.")
@click.option(
    "--workers", default="1,2", show_default=True, help="Worker / actor counts to compare."
)
@set_option("Recipe changes (TrainConfig fields).")
@user_errors
def bench_scaling(env_id: str, updates: int, workers: str, settings: tuple[str, ...]) -> None:
    """Env-steps/s with local worker processes vs Ray actors (needs mat-sdk[ray]).

    \b
    Examples:
      mat bench scaling --updates 3 --set ppo_epochs=1     a quick check
      mat bench scaling --workers 1,4,15 --set device=cuda   a 16-core GPU machine
    """
    from mat_sdk.bench.scaling import main as run

    run(
        env_id,
        updates=updates,
        workers=parse_counts(workers, "--workers"),
        **parse_settings(settings),
    )


@bench.command("loop")
@click.option("--env", "env_id", default="go2:walk", show_default=True)
@click.option("--updates", default=3, show_default=True, help="Updates per variant and round.")
@click.option("--rounds", default=3, show_default=True, help="Interleaved rounds.")
@user_errors
def bench_loop(env_id: str, updates: int, rounds: int) -> None:
    """The training loop's levers one by one (env worker, ONNX acting, update worker,
    torch.compile): rollout, waiting, update and env-steps/s per update, side by side.

    
    Example (the Go2 needs examples/ on the path):
      PYTHONPATH=examples mat bench loop --env go2:walk --updates 3 --rounds 3
    """
    from mat_sdk.bench.loop import main as run

    run(env_id, updates=updates, rounds=rounds)


@bench.command("train")
@click.option("--env", "env_id", default="cheetah-6x1", show_default=True)
@click.option("--device", default="cpu", show_default=True)
@click.option(
    "--compile",
    "compiled",
    is_flag=True,
    help="Also measure torch.compile (~1 min to compile; on CUDA also with CUDA graphs).",
)
@click.option("--rounds", default=3, show_default=True, help="Interleaved rounds per variant.")
@click.option(
    "--workers", default=0, show_default=True, help="Env worker processes for the rollout."
)
@click.option("--threads", type=int, help="torch intra-op threads [the trainer's default, 1].")
@user_errors
def bench_train(
    env_id: str, device: str, compiled: bool, rounds: int, workers: int, threads: int | None
) -> None:
    """Training throughput (paper recipe): rollout vs update, ours vs an official-style update.

    \b
    With a core to spare on a CPU, also our update split with one update worker
    process (mat train --update-workers 1).
    """
    from mat_sdk.bench.train import main as run

    run(env_id, device=device, compiled=compiled, rounds=rounds, workers=workers, threads=threads)
