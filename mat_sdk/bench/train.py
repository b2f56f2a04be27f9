"""Training throughput: the update step against an official-style one, and the recipes side
by side.

First table, the paper's recipe: 40 envs x rollout 100 = 4,000 env-steps per update; 10 epochs
x 40 minibatches of 100 env-steps (all agents together) = 400 optimizer steps per update. Every
update variant runs the same 40 minibatches, interleaved round by round.
Second table, each recipe (`config.RECIPES`): one whole update of the same 4,000 env-steps as
that recipe shapes it, and the env-steps/s it gives with the measured rollout.
"""

from __future__ import annotations

import copy
import time
from functools import partial

import torch

from mat_sdk.bench.reference import OfficialStyleMAT, official_loss
from mat_sdk.common.processes import usable_cores
from mat_sdk.common.timing import compare, print_table
from mat_sdk.policy.config import RECIPES, TrainConfig
from mat_sdk.policy.normalization import ValueNorm
from mat_sdk.training import ppo
from mat_sdk.training.ppo import Rows
from mat_sdk.training.trainer import Trainer
from mat_sdk.training.tuning import twin


def _reference_step(trainer: Trainer, batch: Rows):
    model = OfficialStyleMAT(copy.deepcopy(trainer.policy), trainer.env.n_agents).to(trainer.device)
    # torch's defaults, as the official code has them: for-loops on CPU, foreach on CUDA
    optimizer = torch.optim.Adam(model.parameters(), lr=trainer.config.ppo.lr, eps=1e-5)
    value_norm = ValueNorm(device=trainer.device)

    def step(idx):
        loss = official_loss(model, value_norm, batch[idx], trainer.config.ppo)
        optimizer.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), trainer.config.ppo.max_grad_norm)
        optimizer.step()

    return step


def _keeping_subnormals(step):
    """`step` with subnormal floats computed as such, as torch does by default (the
    trainer flushes them to zero: `RunConfig.flush_denormal`)."""

    def run(idx):
        torch.set_flush_denormal(False)
        try:
            step(idx)
        finally:
            torch.set_flush_denormal(True)

    return run


def _whole_update(trainer: Trainer, batch: Rows):
    """One update as the trainer's config shapes it: epochs x minibatches over `batch`."""
    shape = trainer.config.ppo

    def run():
        for idx in ppo.minibatches(
            len(batch), shape.ppo_epochs, shape.num_minibatches,
            trainer.collector.shuffle_generator, trainer.device,
        ):  # fmt: skip
            trainer.optimizer_step(batch, idx)
        if trainer.device.type == "cuda":
            torch.cuda.synchronize()

    return run


def _recipes(trainer: Trainer, batch, rollout_s: float, rounds: int, split: bool) -> None:
    """The recipes side by side: a whole update each (and with one update worker where a core
    is free), with the rollout measured above."""
    twins: dict[str, Trainer] = {}
    try:
        for recipe in RECIPES:
            settings = TrainConfig.for_algo("mat", recipe)
            ppo = settings.ppo
            shape = {
                "lr": ppo.lr,
                "ppo_epochs": ppo.ppo_epochs,
                "num_minibatches": ppo.num_minibatches,
            }
            twins[recipe] = twin(trainer, batch, **shape)
            if split:
                twins[f"{recipe} + 1 update worker"] = twin(trainer, batch, 1, **shape)
        updates = {name: _whole_update(copied, batch) for name, copied in twins.items()}
        times = compare(updates, seconds=rounds * len(updates) * 2.0, rounds=rounds)
        rows = []
        for name, update_s in times.items():
            cfg = twins[name].config.ppo
            rows.append(
                {
                    "recipe": name,
                    "epochs x minibatches": f"{cfg.ppo_epochs} x {cfg.num_minibatches}",
                    "env-steps / minibatch": f"{batch['obs'].shape[0] // cfg.num_minibatches:,}",
                    "update s / 4000 steps": f"{update_s:.2f}",
                    "rollout s / 4000 steps": f"{rollout_s:.2f}",
                    "env-steps/s": f"{4000 / (rollout_s + update_s):,.0f}",
                    "vs paper": f"{times['paper'] / update_s:.2f}x update",
                }
            )
        print_table(rows, f"Recipes side by side, {trainer.config.env.id}, {trainer.device}")
    finally:
        for copied in twins.values():
            copied.gradients.close()


def main(
    env_id: str = "cheetah-6x1",
    device: str = "cpu",
    compiled: bool = False,
    rounds: int = 3,
    workers: int = 0,
    threads: int | None = None,
) -> None:
    options = {"torch_threads": threads} if threads else {}  # else the trainer's default
    trainer = Trainer(
        env_id, "mat", recipe="paper", num_envs=40, rollout_length=100, device=device,
        workers=workers, **options,
    )  # fmt: skip
    twins: dict[str, Trainer] = {}
    try:
        trainer.rollout()  # warm up the obs normaliser and caches
        start = time.perf_counter()
        rollouts = 2
        for _ in range(rollouts):
            trajectory = trainer.rollout()
        rollout_s = (time.perf_counter() - start) / rollouts
        batch = trajectory.rows()
        size = len(batch) // 40
        minibatches = [torch.arange(i * size, (i + 1) * size) for i in range(40)]
        cpu = trainer.device.type == "cpu"
        split = cpu and usable_cores() > 1  # an update worker needs a core of its own
        twins = {
            "ours, subnormals kept": twin(trainer, batch),
            "ours (default)": twin(trainer, batch),
        }
        if split:
            twins["ours + 1 update worker"] = twin(trainer, batch, update_workers=1)
        if compiled:
            twins["ours + torch.compile"] = twin(trainer, batch, compile_mode="default")
            if split:
                twins["ours + torch.compile + 1 update worker"] = twin(
                    trainer, batch, update_workers=1, compile_mode="default"
                )
            if not cpu:  # the GPU step is launch-bound: CUDA graphs
                twins["ours + torch.compile (CUDA graphs)"] = twin(
                    trainer, batch, compile_mode="reduce-overhead"
                )
        variants = {
            "reference (official style)": _reference_step(trainer, batch),
            "reference, subnormals kept": _keeping_subnormals(_reference_step(trainer, batch)),
        }
        variants |= {name: partial(copied.optimizer_step, batch) for name, copied in twins.items()}
        variants["ours, subnormals kept"] = _keeping_subnormals(variants["ours, subnormals kept"])
        for step in variants.values():  # warm-up (and compilation)
            step(minibatches[0])

        def epoch(step):
            def run():
                for mb in minibatches:
                    step(mb)
                if trainer.device.type == "cuda":
                    torch.cuda.synchronize()

            return run

        times = compare(
            {name: epoch(step) for name, step in variants.items()},
            seconds=rounds * len(variants) * 2.0,
            rounds=rounds,
        )
        reference = times["reference (official style)"]
        rows = []
        for name, epoch_s in times.items():
            update_s = 10 * epoch_s  # 10 epochs of 40 minibatches
            rows.append(
                {
                    "update step": name,
                    "ms / optimizer step": f"{epoch_s / 40 * 1e3:.1f}",
                    "vs reference": f"{reference / epoch_s:.2f}x",
                    "update s / 4000 steps": f"{update_s:.2f}",
                    "rollout s / 4000 steps": f"{rollout_s:.2f}",
                    "rollout share": f"{rollout_s / (rollout_s + update_s):.0%}",
                    "env-steps/s": f"{4000 / (rollout_s + update_s):,.0f}",
                }
            )
        threads = torch.get_num_threads()
        title = (
            f"Training throughput, paper recipe, {env_id}, {trainer.device}, {threads} thread(s)"
        )
        print_table(rows, title)
        _recipes(trainer, batch, rollout_s, rounds, split)
    finally:
        for copied in twins.values():
            copied.gradients.close()
        trainer.close()
