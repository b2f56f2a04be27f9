"""Put a trained run into the model zoo (`zoo/NAME/`), with a card that says what it scores.

    mat zoo add runs/transfer/multi-end-flags/seed_2 swimmer-family-mat \
        --command "python -m mat_sdk.bench.transfer --steps 200000 --out runs/transfer"

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
from pathlib import Path
from typing import Any

import numpy as np
from scipy import stats

from mat_export import export
from mat_runtime.zoo import models, zoo_dir
from mat_sdk import checkpoint
from mat_sdk.bench.seeds import EVALUATION_SEED, random_team_return
from mat_sdk.evaluation import LoadedPolicy, evaluate


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


def add(run: Path, name: str, command: str, episodes: int = 20) -> dict[str, Any]:
    """Copy `run`'s checkpoint into the zoo as `name`, export it, evaluate it, write its card."""
    source = run / "checkpoint.pt" if run.is_dir() else run
    payload = checkpoint.load(source)
    target = zoo_dir() / name
    target.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(source, target / "checkpoint.pt")
    export(target / "checkpoint.pt", target / "onnx", force=True)
    loaded = LoadedPolicy.from_checkpoint(target / "checkpoint.pt")
    returns = evaluate(loaded, episodes, seed=EVALUATION_SEED)
    train = payload["config"]["train"]
    env_id = train["env"]
    options = train.get("env_options") or {}
    random = random_team_return(env_id, episodes, seed=EVALUATION_SEED, **options)
    card = {
        "name": name,
        "env_id": env_id,
        "trained_on": [env_id, *train.get("more_envs", [])],
        "env_options": options,
        "faults": train.get("faults") or {},
        "algo": train["algo"],
        "steps": payload["progress"]["steps"],
        "seed": train["seed"],
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
    (target / "card.json").write_text(json.dumps(card, indent=2) + "\n")
    (target / "card.md").write_text(card_text(card))
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


def cards() -> list[dict[str, Any]]:
    return [json.loads((zoo_dir() / name / "card.json").read_text()) for name in models()]
