"""Train on some agent counts, act on others: the transfer experiment of docs/TRANSFER.md.

    python -m benchmarks.transfer --steps 200000 --seeds 0 1 2 --out runs/transfer

Every run is a `mat train` / `mat finetune` / `mat export` command (printed as it starts), so
each cell can be rerun by hand. Per seed:
- `multi`, `multi-fraction`, `multi-ends`, `multi-near-ends`, `multi-end-flags`: one
  policy trained on the counts `--train` (updates alternating), id-free or with a
  count-independent position identity; `multi-end-flags-window-4` the last with
  `attention_window=4`;
- `single`: the same budget on the middle training count alone;
- `padded`: the official code's approach, every count padded to `--pad` inactive zero agents
  with a one-hot id over them;
- `specialist-K`: from scratch on each unseen count of `--targets`, with the same budget;
- `finetune-K/<multi variant>`: each multi policy adapted to K with `--finetune` x the budget.
Each bundle is then evaluated through `mat_runtime` (no torch) on every count of `--counts`,
`--episodes` deterministic episodes from the same starts, beside a random team and a team held
still (zero actions).

`--cells multi-ends specialist-8 ...` runs a subset (for a costlier family). Finished runs are
skipped and interrupted ones resumed, so re-running continues the experiment; `--report-only`
redraws the table and plot from OUT/results.csv.
"""

from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
from concurrent.futures import ProcessPoolExecutor, ThreadPoolExecutor
from pathlib import Path

import numpy as np
from scipy import stats

from tests.recipes import EVALUATION_SEED

FAMILY = "mamujoco:ManySegmentSwimmer-{}x2"
# The paper's MuJoCo recipe but lr 3e-4, 5 epochs (half the update cost) and gamma 0.999 (a
# swimmer's reward is slow); picked before the experiment, not tuned against alternatives.
RECIPE = {"lr": 3e-4, "ppo_epochs": 5, "gamma": 0.999}
IDENTITIES = {
    "multi": None,
    "multi-fraction": "fraction",
    "multi-ends": "ends",
    "multi-near-ends": "near-ends",
    "multi-end-flags": "end-flags",
}
# Multi cells whose model differs from the recipe's: end-flags with attention limited to the
# 4 nearest agents on each side (linear in the agent count, docs/ALGORITHM.md)
MODELS = {"multi-end-flags-window-4": ("end-flags", {"attention_window": 4})}
FIELDS = ["cell", "seed", "count", "return_mean", "return_std"]
# Teams to compare with: uniform random actions (the normalisation's 0), and zero actions (a
# robot held still: on a walker that earns the alive bonus without any control cost)
REFERENCES = ("random", "still")


def _settings(options: dict | None = None, recipe: dict = RECIPE) -> list[str]:
    pairs = {**recipe, **({"env_options": json.dumps(options)} if options else {})}
    return [arg for key, value in pairs.items() for arg in ("--set", f"{key}={value}")]


def train_cells(args) -> dict[str, tuple[list[str], dict | None]]:
    """{run name: (`mat train` arguments but --out, env options)} for one seed."""
    ids = [args.family.format(k) for k in args.train]
    middle = args.family.format(args.train[len(args.train) // 2])
    # every cell names its identity: `mat train` would give a family position="end-flags"
    id_free = {"position": None}
    cells = {name: ([*ids], {"position": position}) for name, position in IDENTITIES.items()}
    cells |= {name: ([*ids], {"position": position}) for name, (position, _) in MODELS.items()}
    cells["single"] = ([middle], id_free)
    cells["padded"] = ([*ids], {"pad_agents": args.pad, "agent_id": True, **id_free})
    for k in args.targets:
        cells[f"specialist-{k}"] = ([args.family.format(k)], id_free)
    if args.cells:
        unknown = sorted(set(args.cells) - set(cells))
        if unknown:
            raise SystemExit(f"unknown cells {unknown}; the cells are {sorted(cells)}")
        cells = {name: cell for name, cell in cells.items() if name in args.cells}
    return cells


def _run(command: list[str], log: Path) -> None:
    print("$", " ".join(command), flush=True)
    log.parent.mkdir(parents=True, exist_ok=True)
    with log.open("a") as f:
        subprocess.run(command, check=True, stdout=f, stderr=subprocess.STDOUT)


def _model(name: str) -> dict:
    """The model settings a cell adds to the recipe (`MODELS`); none for most cells."""
    return MODELS[name][1] if name in MODELS else {}


def _train(ids: list[str], options, seed: int, steps: int, out: Path, model: dict) -> None:
    if (out / "done").exists():
        return
    resume = ["--resume"] if (out / "checkpoint.pt").exists() else []
    command = ["mat", "train", *ids, "--recipe", "paper"]  # the recipe its results had
    command += ["--seed", str(seed), "--steps", str(steps)]
    command += ["--eval-every", "0"]  # evaluated afterwards, through the runtime
    settings = _settings(options, {**RECIPE, **model})
    _run([*command, "--out", str(out), "--quiet", *resume, *settings], out / "log.txt")
    (out / "done").touch()


def _finetune(checkpoint: Path, env_id: str, steps: int, out: Path) -> None:
    if (out / "done").exists():
        return
    # the checkpoint's recipe; the budget is small, so half-size rollouts give more updates
    command = ["mat", "finetune", str(checkpoint), env_id, "--steps", str(steps)]
    command += ["--out", str(out), "--quiet", "--episodes", "1"]
    _run([*command, *_settings(recipe={"num_envs": 20})], out / "log.txt")
    (out / "done").touch()


def _export(run: Path) -> Path:
    bundle = run / "onnx"
    if not (bundle / "manifest.json").exists():
        _run(
            ["mat", "export", str(run / "checkpoint.pt"), "-o", str(bundle), "--force"],
            run / "log.txt",
        )
    return bundle


def evaluate(bundle: str, counts: list[int], episodes: int, family: str) -> dict:
    """{count: returns} of a bundle acting through the runtime, or of a reference team
    (`REFERENCES`)."""
    from mat_runtime import Policy
    from mat_sdk.envs import make_team

    policy = None if bundle in REFERENCES else Policy.load(bundle)
    options = policy.env_options if policy else {}
    rng = np.random.default_rng(0)
    results = {}
    for count in counts:
        team = make_team(family.format(count), **options)
        returns = []
        for episode in range(episodes):
            obs, total, done = team.reset(seed=EVALUATION_SEED + episode), 0.0, False
            while not done:
                if bundle == "random":
                    actions = rng.uniform(-1, 1, (team.n_agents, team.action_width))
                elif bundle == "still":
                    actions = np.zeros((team.n_agents, team.action_width))
                else:
                    actions = policy.act(obs)
                obs, reward, terminated, truncated = team.step(actions)
                total += reward
                done = terminated or truncated
            returns.append(total)
        results[count] = returns
    return results


def run_experiment(args) -> None:
    out, budget = args.out, args.steps
    tune_steps = max(1, round(args.finetune * budget))
    cells = train_cells(args)
    runs = {(name, seed): out / name / f"seed_{seed}" for name in cells for seed in args.seeds}
    # the long runs (most agents) first, so the pool does not end on one of them
    order = sorted(runs, key=lambda key: -max(_counts(cells[key[0]][0])))
    with ThreadPoolExecutor(args.jobs) as pool:
        jobs = [
            pool.submit(_train, *cells[name], seed, budget, runs[name, seed], _model(name))
            for name, seed in order
        ]
        for job in jobs:
            job.result()
        for k in args.targets:
            for name in [name for name in [*IDENTITIES, *MODELS] if name in cells]:
                for seed in args.seeds:
                    run = out / f"finetune-{k}" / name / f"seed_{seed}"
                    runs[f"finetune-{k}/{name}", seed] = run
                    jobs.append(
                        pool.submit(
                            _finetune,
                            runs[name, seed] / "checkpoint.pt",
                            args.family.format(k),
                            tune_steps,
                            run,
                        )
                    )
        for job in jobs:
            job.result()
        bundles = dict(zip(runs, pool.map(_export, runs.values()), strict=True))
    table = out / "results.csv"
    done = set()
    if table.exists():
        with table.open() as f:
            done = {(r["cell"], int(r["seed"])) for r in csv.DictReader(f)}
    todo = {key: bundle for key, bundle in bundles.items() if key not in done}
    todo |= {(name, 0): name for name in REFERENCES if (name, 0) not in done}
    with ProcessPoolExecutor(args.jobs) as pool:
        futures = {}
        for (name, seed), bundle in todo.items():
            counts = cells_counts(name, args)
            futures[name, seed] = pool.submit(
                evaluate, str(bundle), counts, args.episodes, args.family
            )
        for (name, seed), future in futures.items():
            _append(table, name, seed, future.result())
            print(f"evaluated {name} seed {seed}", flush=True)


def _counts(ids: list[str]) -> list[int]:
    return [int(i.rsplit("-", 1)[1].split("x")[0]) for i in ids]


def cells_counts(name: str, args) -> list[int]:
    """The counts a cell is evaluated on: specialists and fine-tuned runs on their own."""
    if name.startswith(("specialist-", "finetune-")):
        return [int(name.split("/")[0].rsplit("-", 1)[1])]
    return [k for k in args.counts if name != "padded" or k <= args.pad]


def _append(table: Path, cell: str, seed: int, results: dict) -> None:
    new = not table.exists()
    with table.open("a", newline="") as f:
        writer = csv.writer(f)
        if new:
            writer.writerow(FIELDS)
        for count, returns in results.items():
            writer.writerow([cell, seed, count, np.mean(returns), np.std(returns)])
        f.flush()
        os.fsync(f.fileno())


def _normalised(values, specialist, floor: float) -> tuple[float, tuple[float, float]]:
    """A cell's mean return as a fraction of the specialist's, a random team's at 0, and its
    95 % bootstrap CI, the seeds of both resampled (NaN with fewer than 2 seeds of either)."""

    def ratio(cell, best):
        return (np.mean(cell) - floor) / (np.mean(best) - floor)

    if min(len(values), len(specialist)) < 2:
        return ratio(values, specialist), (np.nan, np.nan)
    interval = stats.bootstrap(
        (np.asarray(values), np.asarray(specialist)), ratio, vectorized=False, paired=False,
        n_resamples=2000, method="percentile", random_state=0,
    ).confidence_interval  # fmt: skip
    return ratio(values, specialist), (interval.low, interval.high)


def report(table: Path, plot: Path, targets: list[int]) -> str:
    """Markdown: return per count (mean ± std over seeds) for each cell, then each target's
    ratio to the specialist with the random team at 0, with its bootstrap CI over seeds."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    with table.open() as f:
        rows = list(csv.DictReader(f))
    seeds: dict[tuple[str, int], list[float]] = {}
    for r in rows:
        seeds.setdefault((r["cell"], int(r["count"])), []).append(float(r["return_mean"]))
    cells = list(dict.fromkeys(r["cell"] for r in rows))
    counts = sorted({k for _, k in seeds})
    curves = [c for c in cells if not c.startswith(("specialist-", "finetune-", *REFERENCES))]
    curves += [c for c in REFERENCES if c in cells]  # the references, last

    def cell(name, k):
        values = seeds.get((name, k))
        if not values:
            return ""
        spread = f" ± {np.std(values):.1f}" if len(values) > 1 else ""
        return f"{np.mean(values):.1f}{spread}"

    lines = ["| count | " + " | ".join(curves) + " |", "|---" * (len(curves) + 1) + "|"]
    lines += [f"| {k} | " + " | ".join(cell(c, k) for c in curves) + " |" for k in counts]
    lines += [
        "",
        "| count | cell | seeds | return | vs specialist, random = 0 | 95 % CI |",
        "|---|---|---|---|---|---|",
    ]
    for k in targets:
        specialist = seeds.get((f"specialist-{k}", k))
        if not specialist:
            continue
        floor = np.mean(seeds[("random", k)])
        lines.append(
            f"| {k} | specialist-{k} | {len(specialist)} | {cell(f'specialist-{k}', k)} | 1 | |"
        )
        compared = [c for c in cells if c not in REFERENCES and not c.startswith("specialist-")]
        for name in [c for c in compared if c in curves or c.startswith(f"finetune-{k}/")]:
            values = seeds.get((name, k))
            if not values:
                continue
            ratio, (low, high) = _normalised(values, specialist, floor)
            interval = f"{low:.2f} to {high:.2f}" if np.isfinite(low) else ""
            lines.append(
                f"| {k} | {name} | {len(values)} | {cell(name, k)} | {ratio:.2f} | {interval} |"
            )

    figure, axis = plt.subplots(figsize=(10, 4.5))
    for name in curves:
        ks = [k for k in counts if (name, k) in seeds]
        mean = np.array([np.mean(seeds[name, k]) for k in ks])
        std = np.array([np.std(seeds[name, k]) for k in ks])
        gray = {"random": ":", "still": "--"}
        style = {"linestyle": gray[name], "color": "gray"} if name in gray else {}
        (line,) = axis.plot(ks, mean, marker="o", markersize=3, label=name, **style)
        axis.fill_between(ks, mean - std, mean + std, alpha=0.15, color=line.get_color())
    for name in [c for c in cells if c.startswith(("specialist-", "finetune-"))]:
        k = int(name.split("/")[0].rsplit("-", 1)[1])
        marker = "*" if name.startswith("specialist") else "x"
        values = seeds[name, k]
        axis.errorbar(
            [k],
            [np.mean(values)],
            [np.std(values)],
            fmt=marker,
            markersize=9,
            color="black" if marker == "*" else None,
            label=name,
        )
    axis.set_xlabel("agents (segments)")
    axis.set_ylabel("return (mean ± std over seeds)")
    axis.legend(fontsize=7, ncol=2, loc="upper left", bbox_to_anchor=(1.01, 1))
    axis.grid(alpha=0.3)
    figure.tight_layout()
    figure.savefig(plot, dpi=120)
    return "\n".join(lines)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--family", default=FAMILY, help="an id with {} for the count")
    parser.add_argument("--train", type=int, nargs="+", default=[3, 4, 5])
    parser.add_argument("--targets", type=int, nargs="+", default=[8, 10])
    parser.add_argument("--counts", type=int, nargs="+", default=list(range(2, 13)))
    parser.add_argument("--pad", type=int, default=12, help="the padded baseline's count")
    parser.add_argument("--steps", type=int, default=200_000, help="training env steps")
    parser.add_argument("--finetune", type=float, default=0.05, help="fraction of --steps")
    parser.add_argument("--seeds", type=int, nargs="+", default=[0, 1, 2])
    parser.add_argument("--episodes", type=int, default=5, help="per count and bundle")
    parser.add_argument(
        "--cells", nargs="+", help="run only these training cells (and fine-tune their multi ones)"
    )
    parser.add_argument("--jobs", type=int, default=2, help="runs at once (one core each)")
    parser.add_argument("--out", type=Path, default=Path("runs/transfer"))
    parser.add_argument("--report-only", action="store_true")
    args = parser.parse_args()
    if not args.report_only:
        run_experiment(args)
    text = report(args.out / "results.csv", args.out / "transfer.png", args.targets)
    (args.out / "report.md").write_text(text + "\n")
    print(text)


if __name__ == "__main__":
    sys.exit(main())
