"""`mat train`: a run, or a seed set of runs, as `mat_sdk.training.runs` and
`mat_sdk.training.multiseed` make them."""

from __future__ import annotations

import click
from click.core import ParameterSource

from mat_sdk.cli import main
from mat_sdk.cli.common import (
    fault_option,
    parse_settings,
    quiet_option,
    resumable,
    set_option,
    user_errors,
)
from mat_sdk.common.processes import usable_cores
from mat_sdk.policy.config import DEFAULT_RECIPE, RECIPES, PPOConfig, RunConfig, TrainConfig

# training options with options of their own (field -> the option's parameter)
OWN = {"recipe": "recipe", "num_envs": "num_envs", "workers": "workers",
       "update_workers": "update_workers", "seed": "seed", "device": "device",
       "faults": "faults", "ray": "ray_address"}  # fmt: skip
TRAIN_OPTIONS = {
    "env": "the ENV_ID argument",
    "more_envs": "the ENV_ID arguments after the first",
    "algo": "--algo",
    "recipe": "--recipe",
    "num_envs": "--num-envs",
    "workers": "--workers",
    "update_workers": "--update-workers",
    "seed": "--seed",
    "device": "--device",
    "faults": "--fault NAME=zero|remove|weak:S",
    "ray": "--ray",
}


@main.command()
@click.argument("env_ids", nargs=-1, required=True)
@click.option(
    "--algo",
    default=TrainConfig.algo,
    show_default=True,
    help="mat | mat-dec | mappo | happo (an actor per agent, updated in turn).",
)
@click.option(
    "--recipe",
    type=click.Choice(list(RECIPES)),
    default=DEFAULT_RECIPE,
    show_default=True,
    help="The hyperparameters to start from: fast (5 epochs x 4 large minibatches, lr 3e-4, "
    "clip 0.1 for MAT) or paper (the MAT paper's 10 x 40, lr 5e-5); --set overrides any of them "
    "(docs/ALGORITHM.md).",
)
@click.option(
    "--steps", default=1_000_000, show_default=True, type=click.IntRange(min=1),
    help="Total env steps.",
)  # fmt: skip
@click.option(
    "--num-envs", default=PPOConfig.num_envs, show_default=True, help="Env copies per rollout."
)
@click.option(
    "--workers",
    default=RunConfig.workers,
    show_default=True,
    help="Env worker processes (0: in-process). This process steps a share too when it has a "
    "core left, so on C cores use at most C - 1.",
)
@click.option(
    "--update-workers",
    default=RunConfig.update_workers,
    show_default=True,
    help="Processes that each compute the gradient of a share of every minibatch (CPU; the "
    "same math). On C cores use at most C - 1; with --set compile=true, the fastest update "
    "on 2 cores (BENCHMARKS.md).",
)
@click.option("--seed", default=RunConfig.seed, show_default=True)
@click.option("--device", default=RunConfig.device, show_default=True, help="cpu | cuda | auto")
@click.option(
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    help="Run directory [runs/ENV-ALGO-sSEED].",
)
@click.option(
    "--resume", is_flag=True, help="Continue from OUT/checkpoint.pt exactly where it stopped."
)
@fault_option("Train on a changed robot.")
@set_option()
@click.option(
    "--ray",
    "ray_address",
    is_flag=False,
    flag_value="local",
    default=None,
    metavar="[ADDRESS]",
    help="Rollouts on --workers Ray actors: a local Ray instance, or ADDRESS (e.g. auto).",
)
@click.option(
    "--seeds",
    metavar="S",
    help="Run several seeds: a count (10: seeds 0-9), a range (3-7) or a list (0,4,9); each "
    "in OUT/seed_K, as parallel processes (one per core), or with --ray as Ray tasks over the "
    "cluster's nodes (OUT on storage they all see; a killed task is retried from its "
    "checkpoint). Rerun to resume unfinished seeds.",
)
@click.option(
    "--eval-every",
    type=click.IntRange(min=0),
    help="Evaluate every this many env steps into OUT/evaluations.json (marl-eval layout), "
    "keep the best policy (OUT/best.pt) and end with its absolute metric; 0: off  "
    "[default: the task's recipe's, else steps/20 for runs of 100,000 steps or more, else 0].",
)
@click.option(
    "--eval-episodes", default=10, show_default=True, type=click.IntRange(min=1),
    help="Deterministic episodes per evaluation (the absolute metric: 10x).",
)  # fmt: skip
@click.option(
    "--tune/--no-tune",
    default=None,
    help="Before training, measure the update settings this machine runs fastest (update "
    "workers, torch.compile, subnormal flushing), print them and use them; kept in "
    "OUT/tuning.json for reruns  [default: on for CPU runs of 1,000,000 steps or more; "
    "a setting given on the command line is kept as given].",
)
@quiet_option()
@click.pass_context
@user_errors
def train(
    context, env_ids, algo, recipe, steps, num_envs, workers, update_workers, seed, device, out_dir,
    resume, faults, settings, ray_address, seeds, eval_every, eval_episodes, tune, quiet,
) -> None:  # fmt: skip
    """Train a policy on ENV_ID with PPO (the fast recipe by default; --recipe paper for the
    MAT paper's).

    \b
    Several ids of one family (`mat envs` marks them) train one policy on every agent
    count, updates taking the ids in turn: mat train swimmer-4 swimmer-5 swimmer-6

    \b
    Writes OUT/checkpoint.pt (every 10 updates and at the end), OUT/metrics.csv,
    OUT/tensorboard/ and OUT/learning_curve.png.
    Example: mat train cheetah-6x1 --steps 2000000 --workers 2 --out runs/cheetah

    \b
    ENV_ID may name your own env: module:function, a function returning
    mat_sdk.envs.from_mjcf / from_dm_control / from_pettingzoo (docs/CUSTOM_ENVS.md):
      PYTHONPATH=examples mat train my_robots:arm --steps 24000 --out runs/arm

    \b
    With --ray, --workers counts Ray actors (each steps num-envs/workers copies); needs
    pip install 'mat-sdk[ray]'. A dead worker is replaced and its share re-collected.
    """
    from mat_sdk.training import multiseed, runs

    if ray_address is not None:  # before any measurement or seed starts
        from mat_sdk.training.ray_rollouts import require_ray

        require_ray()
    typed = {
        "recipe": recipe, "num_envs": num_envs, "workers": workers,
        "update_workers": update_workers, "seed": seed, "device": device,
        "faults": faults, "ray": ray_address,
    }  # fmt: skip
    settings = parse_settings(settings, TRAIN_OPTIONS)
    given = [name for name, parameter in OWN.items() if _typed(context, parameter)]
    if seeds is not None and out_dir is None:
        out_dir = multiseed.default_out(env_ids[0], algo)
    request = runs.RunRequest(
        list(env_ids), algo, steps, out_dir, {**typed, **settings}, [*given, *settings],
        resume, eval_every, eval_episodes, tune, free_cores=usable_cores() - 1,
    )  # fmt: skip
    if seeds is not None:
        refused = [f"--{name}" for name in ("seed", "resume") if _typed(context, name)]
        if refused:
            raise click.UsageError(
                f"--seeds runs seed K as `--seed K` and resumes unfinished seeds by itself; "
                f"drop {', '.join(refused)}"
            )
        chosen = multiseed.parse_seeds(seeds)
        failed = multiseed.train_seeds(request, chosen, ray_address, quiet, say=click.echo)
        if failed:
            raise click.ClickException(
                f"seeds {failed} failed (their logs: {request.out}/seed_K/train.log); the "
                "others finished. Run the same command again to resume the failed seeds only"
            )
        click.echo(
            f"all {len(chosen)} seeds finished in {request.out}; compare: mat report {request.out}"
        )
        return
    again = f"mat train {' '.join(env_ids)} --out {request.out} --steps {steps} --resume"
    again += f" --workers {workers}" if workers else ""
    again += f" --device {device}" if device != "cpu" else ""
    with resumable(request.checkpoint, again):
        runs.train(request, say=click.echo, progress_bar=not quiet)
    click.echo(f"checkpoint: {request.checkpoint}")
    click.echo(
        f"metrics:    {request.out / 'metrics.csv'}   curve: {request.out / 'learning_curve.png'}"
    )


def _typed(context: click.Context, parameter: str) -> bool:
    """Whether the user typed this option on the command line (not its default)."""
    return context.get_parameter_source(parameter) == ParameterSource.COMMANDLINE
