"""The `mat` command line. Heavy imports happen inside commands, so `--help` stays instant."""

from __future__ import annotations

import contextlib
import functools
import json
import os
import sys
from collections.abc import Callable, Iterator
from pathlib import Path

import click

from mat_sdk import files
from mat_sdk.config import TrainConfig
from mat_sdk.processes import usable_cores

OUR_PACKAGES = ("mat_sdk", "mat_export", "mat_runtime")
# What our code raises on purpose for a user's mistake; raised from anywhere else, it is a bug.
EXPECTED = (ValueError, OSError, RuntimeError)
# The extra that brings each optional module.
EXTRAS = {"ray": "ray", **dict.fromkeys(
    ("torch", "onnx", "onnxscript", "mujoco", "dm_control", "pettingzoo", "gymnasium",
     "gymnasium_robotics", "tensorboard", "matplotlib", "tqdm", "imageio", "imageio_ffmpeg"),
    "train",
)}  # fmt: skip


def user_errors(command: Callable) -> Callable:
    """Turn a user's mistake into one line and exit code 1; keep the traceback of a bug.

    A mistake is an error our code raises on purpose (`EXPECTED`, raised in one of
    `OUR_PACKAGES`), an OS error about a path (permissions, a full disk), or a missing
    optional package; anything else is a bug, and its traceback is what a bug report needs.
    """

    @functools.wraps(command)
    def wrapper(*args, **kwargs):
        try:
            return command(*args, **kwargs)
        except click.ClickException:
            raise
        except ModuleNotFoundError as error:
            extra = EXTRAS.get((error.name or "").split(".")[0])
            if extra is None:
                _report_bug()
            raise click.ClickException(
                f"{error}. This command needs the {extra} extra: pip install 'mat-sdk[{extra}]'"
            ) from None
        except EXPECTED as error:
            about_a_path = isinstance(error, OSError) and error.filename is not None
            if not (about_a_path or _raised_by_us(error)):
                _report_bug()
            raise click.ClickException(str(error)) from None
        except Exception:
            _report_bug()

    return wrapper


def _raised_by_us(error: BaseException) -> bool:
    """Whether the innermost frame of the error's traceback is in one of our packages."""
    frame = error.__traceback__
    while frame is not None and frame.tb_next is not None:
        frame = frame.tb_next
    module = frame.tb_frame.f_globals.get("__name__", "") if frame else ""
    return module.split(".")[0] in OUR_PACKAGES


def _report_bug() -> None:
    """Print the traceback of the exception being handled and ask for a report; exit 1."""
    import traceback

    traceback.print_exc()
    click.echo(
        "\nmat: this is an unexpected error, a bug in MAT SDK rather than a problem with your "
        "input. Please report it with the traceback above and the command you ran.",
        err=True,
    )
    raise SystemExit(1) from None


@contextlib.contextmanager
def resumable(checkpoint: Path, resume: str) -> Iterator[None]:
    """Ctrl-C: say what the last checkpoint holds and the command that continues from it."""
    try:
        yield
    except KeyboardInterrupt:
        from mat_sdk import checkpoint as checkpoints

        if checkpoint.is_file():
            steps = checkpoints.load(checkpoint)["progress"]["steps"]
            where = f"{checkpoint} holds the run at {steps:,} steps; continue with:\n  {resume}"
        else:
            where = "no checkpoint was written yet; run the same command again to start over"
        click.echo(f"\ninterrupted; {where}", err=True)
        raise SystemExit(130) from None


def parse_faults(values: tuple[str, ...]) -> dict[str, str]:
    """`("bfoot=zero", "agent_2=remove")` -> `{"bfoot": "zero", "agent_2": "remove"}`."""
    faults = {}
    for value in values:
        name, sep, mode = value.partition("=")
        if not sep or not name or mode not in ("zero", "remove"):
            raise click.BadParameter(
                f"{value!r}: use NAME=zero or NAME=remove", param_hint="--fault"
            )
        faults[name] = mode
    return faults


def fault_option(purpose: str) -> Callable:
    """`--fault NAME=zero|remove`, repeatable (see `parse_faults`)."""
    return click.option(
        "--fault", "faults", multiple=True, metavar="NAME=zero|remove", help=purpose
    )


def set_option(purpose: str = "Any TrainConfig field, e.g. lr=3e-4.") -> Callable:
    """`--set KEY=VALUE`, repeatable (see `parse_settings`)."""
    return click.option("--set", "settings", multiple=True, metavar="KEY=VALUE", help=purpose)


def trust_option() -> Callable:
    """`--trust-env-code`: the opt-in to import a `module:function` env id read from a file."""
    return click.option(
        "--trust-env-code",
        is_flag=True,
        help="Import the module:function env id that the checkpoint records (it runs that "
        "module's code): only for files you trust. Built-in ids need no opt-in.",
    )


def quiet_option() -> Callable:
    return click.option("--quiet", is_flag=True, help="No progress bar.")


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
      mat bench seeds                   the learning tests' recipes on many seeds
      mat zoo                           trained models that ship with the project (zoo:NAME)
    """
    # module:function env ids import from the current directory, as `python -m` would
    if os.getcwd() not in sys.path:
        sys.path.append(os.getcwd())


@main.command()
@user_errors
def envs() -> None:
    """List the environment ids with their agents, observation and action sizes.

    \b
    swimmer-N works for any N >= 3 (N - 1 agents); MaMuJoCo scenarios are
    available as mamujoco:<Scenario>-<conf>, e.g. mamujoco:HalfCheetah-6x1;
    coordination-N (any N >= 2) is a one-step discrete game that MAT solves in
    seconds (act: its number of choices). Ids that installed packages register
    under the entry-point group mat_sdk.envs are listed too. [family]: one
    observation size for any agent count (swimmer-N, mamujoco:ManySegmentSwimmer-Kx2,
    mamujoco:ManySegmentAnt-Kx2), so one policy serves them all.
    """
    from mat_sdk.envs import list_envs

    rows = list_envs()
    click.echo(
        "Your own robot or PettingZoo env: an id module:function (e.g. my_robots:arm, "
        "imported from the current directory or PYTHONPATH), see docs/CUSTOM_ENVS.md.\n"
    )
    width = max(26, *(len(r["id"]) for r in rows))
    click.echo(f"{'id':<{width}} {'agents':>6} {'obs':>5} {'act':>4} {'limit':>6}  about")
    for r in rows:
        click.echo(
            f"{r['id']:<{width}} {r['agents']:>6} {r['obs']:>5} {r['act']:>4} "
            f"{r['episode_limit']:>6}  {'[family] ' if r['family'] else ''}{r['about']}"
        )


@main.command()
@click.argument("env_id")
@click.option("--steps", default=1000, show_default=True, help="Env steps to run.")
@click.option("--seed", default=0, show_default=True)
@fault_option("Break a joint or agent.")
@user_errors
def rollout(env_id: str, steps: int, seed: int, faults: tuple[str, ...]) -> None:
    """Roll out a random team on ENV_ID and print the episode returns.

    Example: mat rollout cheetah-6x1 --steps 2000 --fault bfoot=zero
    """
    import numpy as np

    from mat_sdk.envs import make

    env = make(env_id, faults=parse_faults(faults), seed=seed)
    # uniform over each agent's action space, from streams independent of the env's own
    streams = np.random.SeedSequence([seed, 1]).generate_state(len(env.possible_agents))
    for agent, stream in zip(env.possible_agents, streams, strict=True):
        env.action_space(agent).seed(int(stream))
    env.reset(seed=seed)
    click.echo(f"{env_id}: agents {env.agents}, obs {env.observation_space(env.agents[0]).shape}")
    episode_return, returns = 0.0, []
    for _ in range(steps):
        if not env.agents:
            returns.append(episode_return)
            episode_return = 0.0
            env.reset()
        actions = {a: env.action_space(a).sample() for a in env.agents}
        _, rewards, _, _, _ = env.step(actions)
        episode_return += next(iter(rewards.values()))
    returns.append(episode_return)
    click.echo(f"random team, {steps} steps: episode returns {[round(r, 2) for r in returns]}")


def parse_counts(text: str, option: str) -> tuple[int, ...]:
    """`2,6,64` -> (2, 6, 64): positive integers, or a one-line error naming the option."""
    try:
        counts = tuple(int(part) for part in text.split(","))
    except ValueError:
        counts = ()
    if not counts or min(counts) < 1:
        raise click.BadParameter(f"{option} takes positive integers like 2,6,64, got {text!r}")
    return counts


def parse_settings(
    values: tuple[str, ...], own: dict[str, str] | None = None, param_hint: str = "--set"
) -> dict:
    """`("lr=3e-4", "shuffle_agents=true")` -> typed values (JSON, else the text).

    `own`: the fields this command sets through options of their own (field -> option); a
    `--set` of one of them is refused, since the two would contradict each other.
    """
    settings = {}
    for value in values:
        key, sep, raw = value.partition("=")
        if not sep:
            raise click.BadParameter(f"{value!r}: use KEY=VALUE", param_hint=param_hint)
        if own and key in own:
            raise click.BadParameter(
                f"{value!r}: {key} has an option of its own; use {own[key]} instead",
                param_hint=param_hint,
            )
        try:
            settings[key] = json.loads(raw)
        except json.JSONDecodeError:
            settings[key] = raw
    return settings


TRAIN_OPTIONS = {
    "env": "the ENV_ID argument",
    "more_envs": "the ENV_ID arguments after the first",
    "algo": "--algo",
    "num_envs": "--num-envs",
    "workers": "--workers",
    "update_workers": "--update-workers",
    "seed": "--seed",
    "device": "--device",
    "faults": "--fault NAME=zero|remove",
    "ray": "--ray",
}
FINETUNE_OPTIONS = {
    "env": "the ENV_ID argument",
    "more_envs": "the ENV_ID arguments after the first",
    "faults": "--fault NAME=zero|remove",
    "lr": "--lr",
}


@main.group(invoke_without_command=True)
@click.pass_context
@user_errors
def zoo(context: click.Context) -> None:
    """The model zoo: trained policies that ship with the project, used as zoo:NAME.

    \b
    zoo:NAME works wherever a checkpoint or a bundle does:
      mat eval zoo:NAME --episodes 20        reproduces the card's return
      mat finetune zoo:NAME NEW_ENV_ID       adapts it
      mat export zoo:NAME -o DIR             re-exports it
      mat_runtime.Policy.load("zoo:NAME")    its bundle, without torch
    The zoo is zoo/ of a source checkout, or the directory MAT_ZOO names.
    """
    if context.invoked_subcommand is not None:
        return
    from mat_sdk.bench.zoo import cards

    found, problems = cards()
    for problem in problems:
        click.echo(problem, err=True)
    if not found:
        from mat_runtime.zoo import zoo_dir

        click.echo(f"no models in {zoo_dir()}")
        return
    click.echo("| name | env | algo | steps | seed | return (95 % CI) | random team |")
    click.echo("|---|---|---|---|---|---|---|")
    for card in found:
        score = card["return"]
        low, high = score["ci95"]
        click.echo(
            f"| zoo:{card['name']} | {card['env_id']} | {card['algo']} | {card['steps']:,} | "
            f"{card['seed']} | {score['mean']:.1f} ({low:.1f} to {high:.1f}) | "
            f"{card['random_team_return']:.1f} |"
        )


@zoo.command("add")
@click.argument("run", type=click.Path(exists=True, path_type=Path))
@click.argument("name")
@click.option("--command", "made_by", required=True, help="The command that trained it.")
@click.option(
    "--episodes", default=20, show_default=True, type=click.IntRange(min=1),
    help="Episodes the card reports.",
)  # fmt: skip
@click.option("--force", is_flag=True, help="Replace a model of that name.")
@trust_option()
@user_errors
def zoo_add(
    run: Path, name: str, made_by: str, episodes: int, force: bool, trust_env_code: bool
) -> None:
    """Add RUN (a run directory or checkpoint) to the zoo as NAME, with its card.

    NAME is letters, digits, '.', '_' and '-'. The model is exported, evaluated and written
    beside the zoo, then moved into place: a failure leaves the zoo as it was.
    """
    from mat_sdk.bench.zoo import add, card_text

    card = add(run, name, made_by, episodes, force=force, trust_env_code=trust_env_code)
    click.echo(card_text(card))


@main.command()
@click.argument("runs", nargs=-1, required=True, type=click.Path(exists=True, path_type=Path))
@click.option(
    "--out", "out_dir", required=True, type=click.Path(file_okay=False, path_type=Path),
    help="Directory for report.md and the curves.",
)  # fmt: skip
@user_errors
def report(runs, out_dir) -> None:
    """Compare runs the way the field asks: IQM and mean with 95 % bootstrap CIs.

    RUNS are run directories (or their parents, e.g. the OUT of `mat train --seeds`) holding
    evaluations.json. Per task: IQM and mean over seeds of each seed's absolute metric, with
    stratified-bootstrap confidence intervals (rliable), sample-efficiency curves with CI
    bands, and the probability of improvement between algorithms. Needs
    pip install 'mat-sdk[report]'.

    \b
    Example:
      mat train cheetah-6x1 --seeds 5 --steps 2000000 --out runs/cheetah-mat
      mat train cheetah-6x1 --seeds 5 --steps 2000000 --algo mappo --out runs/cheetah-mappo
      mat report runs/cheetah-mat runs/cheetah-mappo --out docs/cheetah
    """
    try:
        import rliable  # noqa: F401
    except ImportError:
        raise click.ClickException(
            "mat report needs rliable: pip install 'mat-sdk[report]'"
        ) from None
    from mat_sdk.report import write_report

    click.echo(write_report(list(runs), out_dir))
    click.echo(f"written: {out_dir / 'report.md'}")


@main.command()
@click.argument("env_ids", nargs=-1, required=True)
@click.option("--algo", default=TrainConfig.algo, show_default=True, help="mat | mat-dec | mappo")
@click.option(
    "--steps", default=1_000_000, show_default=True, type=click.IntRange(min=1),
    help="Total env steps.",
)  # fmt: skip
@click.option(
    "--num-envs", default=TrainConfig.num_envs, show_default=True, help="Env copies per rollout."
)
@click.option(
    "--workers",
    default=TrainConfig.workers,
    show_default=True,
    help="Env worker processes (0: in-process). This process steps a share too when it has a "
    "core left, so on C cores use at most C - 1.",
)
@click.option(
    "--update-workers",
    default=TrainConfig.update_workers,
    show_default=True,
    help="Processes that each compute the gradient of a share of every minibatch (CPU; the "
    "same math). On C cores use at most C - 1; with --set compile=true, the fastest update "
    "on 2 cores (BENCHMARKS.md).",
)
@click.option("--seed", default=TrainConfig.seed, show_default=True)
@click.option("--device", default=TrainConfig.device, show_default=True, help="cpu | cuda | auto")
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
    "[default: steps/20 for runs of 100,000 steps or more, else 0].",
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
@user_errors
def train(
    env_ids,
    algo,
    steps,
    num_envs,
    workers,
    update_workers,
    seed,
    device,
    out_dir,
    resume,
    faults,
    settings,
    ray_address,
    seeds,
    eval_every,
    eval_episodes,
    tune,
    quiet,
) -> None:
    """Train a policy on ENV_ID with PPO (the paper's MA-MuJoCo recipe by default).

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
    from mat_sdk.trainer import CHECKPOINT_NAME, Trainer

    env_id = env_ids[0]
    if ray_address is not None:  # before any measurement or seed starts
        from mat_sdk.ray_rollouts import require_ray

        require_ray()
    if eval_every is None:
        eval_every = steps // 20 if steps >= 100_000 else 0
    if seeds is not None:
        _train_seeds(click.get_current_context(), env_ids, seeds, out_dir, eval_every, tune)
        return
    out = Path(out_dir or f"runs/{env_id.replace(':', '_')}-{algo}-s{seed}")
    click.get_current_context().with_resource(files.RunLock(out))  # one run at a time in OUT
    ckpt = out / CHECKPOINT_NAME
    asked = _train_options(click.get_current_context().params)
    if resume:
        if not ckpt.exists():
            raise FileNotFoundError(f"nothing to resume: {ckpt} does not exist")
        given = _given_on_the_command_line(click.get_current_context(), asked)
        overrides = _resume_overrides(ckpt, given)
        # the ids typed here are the checkpoint's (`_resume_overrides` refuses others)
        trainer = Trainer.load(ckpt, out_dir=out, trust_env_code=True, **overrides)
        changed = ", ".join(f"{k}={v}" for k, v in overrides.items())
        click.echo(
            f"resuming {ckpt} at {trainer.progress['steps']:,} steps"
            + (f" (with {changed})" if changed else "")
        )
    else:
        if ckpt.exists():
            raise FileExistsError(
                f"{ckpt} exists; pass --resume to continue that run or choose another --out"
            )
        asked["env_options"] = _family_identity(env_id, asked.get("env_options") or {})
        context = click.get_current_context()
        asked |= _tuned(context, asked, out, tune, free_cores=usable_cores() - 1)
        trainer = Trainer(asked.pop("env"), asked.pop("algo"), out_dir=out, **asked)
    planned = trainer.planned_steps(steps)
    if planned != steps and planned > trainer.progress["steps"]:
        per_update = trainer.config.num_envs * trainer.config.rollout_length
        click.echo(
            f"--steps {steps:,}: training runs whole updates of {per_update:,} env steps "
            f"(num_envs x rollout_length), so this run ends at {planned:,} steps"
        )
    again = f"mat train {' '.join(env_ids)} --out {out} --steps {steps} --resume"
    again += f" --workers {workers}" if workers else ""
    if trainer.config.update_workers:
        again += f" --update-workers {trainer.config.update_workers}"
    again += f" --device {device}" if device != "cpu" else ""
    evaluations = None
    if eval_every:
        from mat_sdk.protocol import EvaluationLog

        evaluations = EvaluationLog(out, eval_every, eval_episodes)
        click.echo(
            f"evaluating every {eval_every:,} steps on {eval_episodes} episodes into "
            f"{evaluations.path} (--eval-every 0: off)"
        )
    with resumable(ckpt, again), trainer:
        trainer.learn(steps, callback=evaluations, progress_bar=not quiet)
        if evaluations is not None and trainer.progress["steps"] >= steps:
            absolute = evaluations.finish(trainer)
            if absolute is not None:
                import numpy as np

                click.echo(
                    f"absolute metric (best policy, {len(absolute)} episodes): "
                    f"{np.mean(absolute):.2f} ± {np.std(absolute):.2f}"
                )
    click.echo(f"checkpoint: {ckpt}")
    click.echo(f"metrics:    {out / 'metrics.csv'}   curve: {out / 'learning_curve.png'}")


def _train_options(params: dict) -> dict:
    """`mat train`'s command line as `Trainer` options (`env` and `algo` included)."""
    env_ids = params["env_ids"]
    asked = {
        "env": env_ids[0],
        "algo": params["algo"],
        **{name: params[name] for name in ("num_envs", "workers", "update_workers", "seed")},
        "device": params["device"],
        "faults": parse_faults(params["faults"]),
        "ray": params["ray_address"],
        # one policy on several counts of a family, updates in turn; always given, so a
        # resume names every id its checkpoint records
        "more_envs": list(env_ids[1:]),
        **parse_settings(params["settings"], TRAIN_OPTIONS),
    }
    return asked


def _tuned(context: click.Context, asked: dict, out: Path, tune: bool | None, free_cores: int):
    """The update settings measured fastest on this machine (`mat_sdk.tuning`), for
    a run that asks for them (`--tune`) or a long CPU run by default; those the command line
    gives stay as given. -> {field: value} to train with ({} when not tuning)."""
    from mat_sdk.tuning import TUNED, tuned_settings, wanted

    given = _given_on_the_command_line(context, asked)
    fixed = {name: given[name] for name in TUNED if name in given}
    on_cpu = asked["device"] == "cpu" or (asked["device"] == "auto" and not _cuda())
    if not wanted(tune, context.params["steps"], on_cpu, fixed):
        return {}
    # a seed set comes here before its seeds add the family identity themselves
    options = _family_identity(asked["env"], asked.get("env_options") or {})
    run = {**asked, "env_options": options}
    return tuned_settings(out, run, fixed, max(0, free_cores), echo=click.echo)


def _cuda() -> bool:
    import torch

    return torch.cuda.is_available()


# measured best of none / fraction / ends / near-ends / end-flags (docs/TRANSFER.md)
FAMILY_IDENTITY = "end-flags"


def _family_identity(env_id: str, options: dict) -> dict:
    """A new run on a family (`mat envs` marks them) gets the count-independent identity
    that transferred best across counts, unless the options name one (null: none). The
    checkpoint records it, so every tool rebuilds the same observations."""
    from mat_sdk import envs

    if "position" in options:
        return options
    try:
        team = envs.make_team(env_id, **options)
    except (ValueError, TypeError):
        return options  # the trainer reports what is wrong with the env
    if not team.variable_count:
        return options
    click.echo(
        f"{env_id} is a family: agents observe position={FAMILY_IDENTITY!r} (whether an agent "
        "is at an end of the chain, docs/TRANSFER.md); --set 'env_options={\"position\": null}' "
        "for none"
    )
    return {**options, "position": FAMILY_IDENTITY}


def _train_seeds(
    context: click.Context, env_ids, seeds: str, out_dir, eval_every: int, tune: bool | None
) -> None:
    """`mat train ... --seeds S`: each seed as its own `mat train --seed K` process; the
    update settings are tuned once, here, and given to every seed."""
    from click.core import ParameterSource

    from mat_sdk.multiseed import parse_seeds, ray_launcher, run_seeds

    params = context.params
    refused = [f"--{name}" for name in ("seed", "resume")
               if context.get_parameter_source(name) == ParameterSource.COMMANDLINE]  # fmt: skip
    if refused:
        raise click.UsageError(
            f"--seeds runs seed K as `--seed K` and resumes unfinished seeds by itself; drop "
            f"{', '.join(refused)}"
        )
    chosen = parse_seeds(seeds)
    out = Path(out_dir or f"runs/{env_ids[0].replace(':', '_')}-{params['algo']}")
    context.with_resource(files.RunLock(out))  # one seed set at a time in OUT
    asked = _train_options(params)
    # tuned so that no seed waits for a core: each keeps its share of them
    share = usable_cores() // min(len(chosen), usable_cores())
    tuned = _tuned(context, asked, out, tune, free_cores=share - 1 - params["workers"])
    update_workers = tuned.pop("update_workers", params["update_workers"])
    args = [*env_ids, "--algo", params["algo"], "--steps", str(params["steps"]), "--no-tune"]
    for name in ("num_envs", "workers", "device", "eval_episodes"):
        args += [f"--{name.replace('_', '-')}", str(params[name])]
    args += ["--update-workers", str(update_workers), "--eval-every", str(eval_every)]
    for fault in params["faults"]:
        args += ["--fault", fault]
    for setting in params["settings"]:
        args += ["--set", setting]
    for name, value in tuned.items():
        args += ["--set", f"{name}={json.dumps(value)}"]
    per_seed = 1 + params["workers"] + update_workers
    if params["ray_address"] is None:
        processes = max(1, min(len(chosen), usable_cores() // per_seed))
        click.echo(f"{len(chosen)} seeds into {out}/seed_K, {processes} at a time")
        launch = {}
    else:  # every seed a Ray task of per_seed CPUs, queued by Ray; OUT on storage every node sees
        processes = len(chosen)
        launch = {"launch": ray_launcher(params["ray_address"], per_seed)}
        click.echo(f"{len(chosen)} seeds into {out}/seed_K as Ray tasks of {per_seed} CPU(s)")
    failed = run_seeds(args, chosen, out, params["steps"], processes, params["quiet"], **launch)
    if failed:
        raise click.ClickException(
            f"seeds {failed} failed (their logs: {out}/seed_K/train.log); the others finished. "
            "Run the same command again to resume the failed seeds only"
        )
    click.echo(f"all {len(chosen)} seeds finished in {out}; compare them: mat report {out}")


def _given_on_the_command_line(context: click.Context, asked: dict) -> dict:
    """The fields of `asked` the user set on this command line: typed options and --set."""
    from click.core import ParameterSource

    parameters = {"env": "env_ids", "faults": "faults", "ray": "ray_address"}
    given = {}
    for field, value in asked.items():
        parameter = parameters.get(field, field)
        from_set = parameter not in context.params  # no option of its own
        if from_set or context.get_parameter_source(parameter) == ParameterSource.COMMANDLINE:
            given[field] = value
    return given


def _resume_overrides(ckpt: Path, given: dict) -> dict:
    """What a resume may change (how it runs) from `given`; anything else that differs from
    the checkpoint's run is refused in one line, never dropped."""
    from mat_sdk import checkpoint as checkpoints

    train = checkpoints.load(ckpt)["config"]["train"]
    overrides = {}
    for field, value in given.items():
        if field in checkpoints.RESUME_OVERRIDES:
            overrides[field] = value
        elif field not in train:
            raise click.BadParameter(f"{field} is not a training option", param_hint="--set")
        elif value != train[field]:
            raise click.UsageError(
                f"--resume continues {ckpt} as it was trained, with {field}={train[field]!r}; "
                f"got {field}={value!r}. Drop that option, or start a new run with another --out"
            )
    return overrides


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
    from mat_sdk.evaluation import LoadedPolicy, evaluate_episodes

    loaded = LoadedPolicy.from_checkpoint(checkpoint)
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
    resume,
    settings,
    trust_env_code,
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
    """
    import numpy as np

    from mat_sdk.checkpoint import CHECKPOINT_NAME
    from mat_sdk.finetune import finetune as run

    fault_map = parse_faults(faults)
    label = "-".join(f"{k}_{v}" for k, v in fault_map.items()) or (env_id or "same")
    out = Path(out_dir or f"runs/finetune-{label.replace(':', '_')}")
    again = f"mat finetune {checkpoint} --out {out} --steps {steps} --resume"
    options = parse_settings(settings, FINETUNE_OPTIONS)
    if resume and (out / CHECKPOINT_NAME).exists():  # the run goes on as it was started
        asked = {"env": env_id, "faults": fault_map or None, "lr": lr, **options}
        options = _resume_overrides(
            out / CHECKPOINT_NAME, {k: v for k, v in asked.items() if v is not None}
        )
    with resumable(out / CHECKPOINT_NAME, again):
        result = run(
            checkpoint,
            env=env_id,
            faults=fault_map,
            steps=steps,
            out_dir=out,
            eval_episodes=episodes,
            reset_optimizer=not keep_optimizer,
            lr=lr,
            resume=resume,
            progress_bar=not quiet,
            trust_env_code=trust_env_code,
            **options,
        )
    result.trainer.close()
    click.echo(
        f"zero-shot return {result.zero_shot_mean:.1f} ± {np.std(result.zero_shot):.1f} -> "
        f"after {result.trainer.progress['steps']:,} steps {result.final_mean:.1f} ± "
        f"{np.std(result.final):.1f} ({episodes} episodes each)"
    )
    click.echo(f"checkpoint: {out / 'checkpoint.pt'}   summary: {out / 'finetune.json'}")


@main.command("export")
@click.argument("checkpoint", type=click.Path())
@click.option(
    "-o",
    "--out",
    "out_dir",
    type=click.Path(file_okay=False),
    help="Bundle directory [CHECKPOINT_onnx].",
)
@click.option("--force", is_flag=True, help="Replace an existing bundle directory.")
@trust_option()
@user_errors
def export_command(checkpoint: str, out_dir: str | None, force: bool, trust_env_code: bool) -> None:
    """Export CHECKPOINT to an ONNX bundle for the torch-free runtime.

    \b
    Writes encoder.onnx, decoder_step.onnx (KV-cached single-agent step) and manifest.json,
    after checking ONNX Runtime against torch on 1, 2, 6, 17 and 64 agents; a bundle that
    disagrees by more than 1e-4 is refused and nothing is written.
    Example: mat export runs/cheetah/checkpoint.pt -o cheetah_onnx
    """
    from mat_export import export

    target = (
        Path(out_dir) if out_dir else Path(checkpoint).with_name(Path(checkpoint).stem + "_onnx")
    )
    manifest = export(checkpoint, target, force=force, trust_env_code=trust_env_code)
    worst = max(manifest["parity"]["max_abs_diff"].values())
    counts = ", ".join(manifest["parity"]["max_abs_diff"])
    graphs = ", ".join(f"{name} (opset {g['opset']})" for name, g in manifest["graphs"].items())
    click.echo(f"{target}: {manifest['algo']} ({manifest['kind']}): {graphs}")
    click.echo(f"ORT vs torch max abs diff {worst:.2e} over agent counts {counts}")


@main.group()
def bench() -> None:
    """Benchmarks that print Markdown tables (paste them into BENCHMARKS.md)."""


@bench.command("envs")
@click.option("--seconds", default=1.0, show_default=True, help="Time per measured variant.")
@user_errors
def bench_envs(seconds: float) -> None:
    """Our env step vs dm_control's bare physics step, and vectorised rates."""
    from mat_sdk.bench.envs import main as run

    run(seconds=seconds)


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


@bench.command("seeds")
@click.option(
    "--recipe",
    "recipes",
    multiple=True,
    help="A learning test's recipe (repeatable) [all]: game-mat, game-mat-dec, game-onnx, "
    "finetune, finetune-gain, continuous, arm, spread, spread-continuous.",
)
@click.option("--seeds", default=16, show_default=True, help="Seeds 0..N-1 (or --first).")
@click.option("--first", default=0, show_default=True, help="The first seed.")
@click.option("--processes", type=int, help="Runs at a time [one per core].")
@user_errors
def bench_seeds(recipes: tuple[str, ...], seeds: int, first: int, processes: int | None) -> None:
    """The learning tests' recipes on many seeds: does each test's bound hold on every seed?

    \b
    Each recipe trains exactly what its test trains (seconds per run on one core).
    Examples:
      mat bench seeds --recipe game-mat --seeds 16
      mat bench seeds --seeds 4 --first 100      every recipe on seeds 100-103
    """
    from mat_sdk.bench.seeds import RECIPES
    from mat_sdk.bench.seeds import main as run

    unknown = set(recipes) - set(RECIPES)
    if unknown:
        raise click.BadParameter(
            f"unknown recipe(s) {sorted(unknown)}; valid: {', '.join(RECIPES)}",
            param_hint="--recipe",
        )
    if seeds < 1 or first < 0:
        raise click.BadParameter("--seeds must be >= 1 and --first >= 0")
    run(recipes or tuple(RECIPES), range(first, first + seeds), processes)
