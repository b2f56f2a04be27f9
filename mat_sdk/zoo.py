"""Put a trained run into the model zoo (`zoo/NAME/`), with a card that says what it scores.

    mat zoo add runs/transfer/multi-end-flags/seed_2 swimmer-family-mat \
        --command "python -m benchmarks.transfer --steps 200000 --out runs/transfer"

Copies the checkpoint, exports its bundle, evaluates it as `mat eval zoo:NAME --episodes N`
does (deterministic, the same starts) beside a random team, and writes `card.json` and
`card.md`: env, algorithm, steps, seed, the return with a 95 % bootstrap CI over episodes
(scipy), the command and commit that made it.
"""

from __future__ import annotations

import datetime
import json
import shutil
import subprocess
import tempfile
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from mat_export import export
from mat_runtime.zoo import NAME, models, zoo_dir
from mat_sdk import envs
from mat_sdk.common import files
from mat_sdk.evaluation.episodes import (
    EVALUATION_SEED,
    CheckpointPolicy,
    evaluate,
    random_team_return,
)
from mat_sdk.policy import checkpoint


def _commit() -> str:
    try:
        return subprocess.run(
            ["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True, check=True,
            cwd=Path(__file__).parent,
        ).stdout.strip()  # fmt: skip
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def _interval(returns: list[float]) -> list[float]:
    """95 % bootstrap confidence interval of the mean return over episodes."""
    if len(set(returns)) < 2:
        return [float(returns[0])] * 2
    result = stats.bootstrap(
        (np.asarray(returns),), np.mean, confidence_level=0.95, n_resamples=9999,
        random_state=np.random.default_rng(0),
    )  # fmt: skip
    return [float(result.confidence_interval.low), float(result.confidence_interval.high)]


def add(
    run: Path,
    name: str,
    command: str,
    episodes: int = 20,
    force: bool = False,
) -> dict[str, Any]:
    """Copy `run`'s checkpoint into the zoo as `name`, export it, evaluate it, write its card.

    Everything is built in a directory beside the zoo's models and moved into place at the
    end, so a failure leaves the zoo as it was; a model of that name is replaced only with
    `force`. A `module:function` env id that the checkpoint records is imported (to export
    and evaluate it) only for a run given as `envs.Trusted(run)`."""
    if not isinstance(name, str) or not NAME.fullmatch(name) or ".." in name:
        raise ValueError(
            f"zoo name {name!r}: use letters, digits, '.', '_' and '-' (starting with a letter "
            "or digit), as in zoo:NAME"
        )
    if isinstance(episodes, bool) or not isinstance(episodes, int) or episodes < 1:
        raise ValueError(f"episodes must be an integer >= 1, got {episodes!r}")
    source = Path(run) / "checkpoint.pt" if Path(run).is_dir() else Path(run)
    payload = checkpoint.load(source)
    train = checkpoint.recorded_config(payload)
    env_id = train.env.id
    envs.check_trusted([env_id], envs.trusted_as(source, run))
    target = zoo_dir() / name
    if target.exists() and not force:
        raise FileExistsError(
            f"the zoo has a model {name!r} ({target}); pass --force (force=True) to replace it"
        )
    with files.writing(zoo_dir()):
        zoo_dir().mkdir(parents=True, exist_ok=True)
        staging = Path(tempfile.mkdtemp(prefix=f".{name}.", dir=zoo_dir()))
    try:
        with files.writing(target):
            shutil.copyfile(source, staging / "checkpoint.pt")
        copied = envs.trusted_as(staging / "checkpoint.pt", run)
        export(copied, staging / "onnx")
        loaded = CheckpointPolicy.from_checkpoint(copied)
        returns = evaluate(loaded, episodes, seed=EVALUATION_SEED)
        options = dict(train.env.options)
        random = random_team_return(env_id, episodes, seed=EVALUATION_SEED, **options)
        card = {
            "name": name,
            "env_id": env_id,
            "trained_on": train.env.ids,
            "env_options": options,
            "faults": envs.as_mapping(train.env.faults),
            "algo": train.algo,
            "steps": payload["progress"]["steps"],
            "seed": train.run.seed,
            "return": {
                "mean": float(np.mean(returns)),
                "ci95": _interval(returns),
                "std": float(np.std(returns)),
                "episodes": episodes,
                "returns": returns,
                "evaluation_seed": EVALUATION_SEED,
                "command": f"mat eval zoo:{name} --episodes {episodes}",
            },
            "random_team_return": random,
            "made_by": command,
            "commit": _commit(),
            "date": datetime.date.today().isoformat(),
        }
        files.write_text_atomic(staging / "card.json", json.dumps(card, indent=2) + "\n")
        files.write_text_atomic(staging / "card.md", card_text(card))
        with files.writing(target):
            staging.chmod(0o755)  # mkdtemp makes 0700
            files.replace_directory(staging, target)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return card


def card_text(card: dict[str, Any]) -> str:
    score = card["return"]
    low, high = score["ci95"]
    return (
        f"# {card['name']}\n\n"
        f"- env: `{card['env_id']}` (trained on {', '.join(card['trained_on'])}; options "
        f"{card['env_options'] or 'none'}; faults {card['faults'] or 'none'})\n"
        f"- algorithm: {card['algo']}, {card['steps']:,} env steps, seed {card['seed']}\n"
        f"- return: **{score['mean']:.2f}** (95 % CI {low:.2f} to {high:.2f}, std "
        f"{score['std']:.2f}) over {score['episodes']} deterministic episodes from seed "
        f"{score['evaluation_seed']}: `{score['command']}`; a random team: "
        f"{card['random_team_return']:.2f}\n"
        f"- made by: `{card['made_by']}` at commit {card['commit']}, {card['date']}\n"
    )


CARD_FIELDS = {
    "name": str,
    "env_id": str,
    "algo": str,
    "steps": int,
    "seed": int,
    "return": dict,
    "random_team_return": (int, float),
}
RETURN_FIELDS = {"mean": (int, float), "ci95": list}


def cards() -> tuple[list[dict[str, Any]], list[str]]:
    """The zoo's cards, and one line per card that cannot be read (so one broken card does
    not hide the others)."""
    found, problems = [], []
    for name in models():
        path = zoo_dir() / name / "card.json"
        try:
            card = json.loads(path.read_text())
            problem = _card_problem(card)
        except (OSError, UnicodeDecodeError, ValueError, RecursionError) as error:
            problem = f"cannot be read ({type(error).__name__})"
        if problem:
            problems.append(f"{path}: {problem}; skipped (`mat zoo add --force` remakes it)")
        else:
            found.append(card)
    return found, problems


def _card_problem(card: Any) -> str | None:
    if not isinstance(card, dict):
        return f"is a {type(card).__name__}, not a card"
    for fields, within in ((CARD_FIELDS, card), (RETURN_FIELDS, card.get("return", {}))):
        for key, kind in fields.items():
            value = within.get(key)
            if isinstance(value, bool) or not isinstance(value, kind):
                return f"{key} is missing or not a {getattr(kind, '__name__', 'number')}"
    low_high = card["return"]["ci95"]
    if len(low_high) != 2 or not all(isinstance(v, int | float) for v in low_high):
        return "return.ci95 is not two numbers"
    return None
