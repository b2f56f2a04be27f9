"""PPO trainer: learning (honest, seconds), exact resume, crash safety, clear errors."""

import dataclasses
import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import torch
from helpers import GAME

from mat_sdk import envs
from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate_episodes
from mat_sdk.policy import checkpoint
from mat_sdk.training.rollout import Trajectory
from mat_sdk.training.trainer import TrainConfig, Trainer, TrainingDiverged
from tests import recipes

DATA = Path(__file__).parent / "data"


def test_mat_solves_the_coordination_game_and_decentralised_actors_cannot():
    """One seed is safe: `python -m benchmarks.seeds --recipe game-mat --recipe game-mat-dec`
    shows the bounds hold on every seed swept (BENCHMARKS.md)."""
    mat, dec = recipes.game_return("mat"), recipes.game_return("mat-dec")
    assert mat >= 0.9, mat  # random play scores 2/27 = 0.07
    assert dec <= 0.5, dec  # decentralised actors can reach at most 1/3
    assert mat - dec >= 0.4


def test_happo_reaches_the_decentralised_best_on_the_coordination_game_and_no_more():
    """`python -m benchmarks.seeds --recipe game-happo`: every seed swept ends near 1/3
    (BENCHMARKS.md)."""
    happo = recipes.game_return("happo")
    assert happo >= 0.25, happo  # random play: 2/27 = 0.07; decentralised best: 1/3
    assert happo <= 0.5, happo  # an actor per agent still cannot see the others' choices


def test_short_continuous_run_beats_a_random_team():
    bound = recipes.continuous_bound()
    learned = recipes.continuous_return()
    assert learned >= bound, (learned, bound)


def test_short_continuous_happo_run_beats_a_random_team():
    """`python -m benchmarks.seeds --recipe continuous-happo`: 2.7-4.2 on seeds 0-3 against 2."""
    bound = recipes.continuous_bound()
    learned = recipes.continuous_return(algo="happo")
    assert learned >= bound, (learned, bound)


TINY = {
    "num_envs": 3,
    "rollout_length": 10,
    "ppo_epochs": 2,
    "num_minibatches": 2,
    "lr": 1e-3,
    "checkpoint_every": 1,
    "env_options": {"episode_limit": 15},
}


TIMING = ("rollout_s", "update_s", "steps_per_s")


def logged_rows(run_dir) -> list[dict]:
    """metrics.csv without its timing columns, which no two runs share."""
    from mat_sdk.training.run_log import read_metrics

    rows = read_metrics(run_dir / "metrics.csv")
    return [{k: v for k, v in row.items() if k not in TIMING} for row in rows]


def finished_state(trainer: Trainer) -> tuple[dict, checkpoint.Progress]:
    weights = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    return weights, dataclasses.replace(trainer.progress)


def assert_same_run(a: tuple[dict, dict], b: tuple[dict, dict], a_dir, b_dir) -> None:
    """Same weights, same progress and the same logged rows."""
    (a_weights, a_progress), (b_weights, b_progress) = a, b
    assert list(a_weights) == list(b_weights)
    for name, value in a_weights.items():
        assert torch.equal(value, b_weights[name]), name
    assert a_progress == b_progress
    assert logged_rows(a_dir) == logged_rows(b_dir)


RESUMABLE = {
    "in-process hopper": ("hopper-4x1", {}),
    "MaMuJoCo": ("mamujoco:HalfCheetah-6x1", {}),
    "env workers": ("hopper-4x1", {"workers": 1}),
    "update workers": pytest.param("hopper-4x1", {"update_workers": 1}, marks=pytest.mark.slow),
    "ONNX rollouts": ("hopper-4x1", {"rollout_backend": "onnx"}),
    "several agent counts": ("swimmer-4", {"more_envs": ["swimmer-5", "swimmer-6"]}),
    "compiled": pytest.param("hopper-4x1", {"compile": True}, marks=pytest.mark.slow),
    "HAPPO": ("hopper-4x1", {"algo": "happo"}),
    "adaptive learning rate": ("hopper-4x1", {"desired_kl": 0.002}),
}


def test_each_update_logs_what_says_whether_learning_can_still_move(tmp_path):
    """advantage_std, explained_variance and action_std: the columns a stalled run is traced by."""
    with Trainer("hopper-2x2", "mat", out_dir=tmp_path, **TINY) as trainer:
        trainer.learn(60, progress_bar=False)
    rows = logged_rows(tmp_path)
    assert len(rows) == 2
    for row in rows:
        assert float(row["advantage_std"]) > 0
        assert float(row["explained_variance"]) <= 1.0
        assert 0 < float(row["action_std"]) <= 0.5  # the official std: sigmoid(log_std) * 0.5


def test_explained_variance_is_one_for_exact_values_and_zero_for_their_mean():
    returns = torch.arange(12.0).reshape(3, 2, 2, 1)
    unread = ("obs", "actions", "log_probs", "rewards", "terminated", "done")
    base = Trajectory(
        **{k: torch.zeros(3, 2, 2, 1) for k in unread},
        values=returns,
        bootstrap=torch.zeros(3, 2, 2, 1),
        last_values=torch.zeros(2, 2, 1),
        finished=[],
        advantages=torch.zeros_like(returns),
        returns=returns,
    )
    exact = base.diagnostics()
    assert exact["explained_variance"] == 1.0 and exact["advantage_std"] == 0.0
    mean_only = dataclasses.replace(base, advantages=returns - returns.mean())
    assert mean_only.diagnostics()["explained_variance"] == pytest.approx(0.0, abs=1e-6)


@pytest.mark.parametrize(("env_id", "options"), list(RESUMABLE.values()), ids=list(RESUMABLE))
def test_interrupted_and_resumed_run_matches_an_uninterrupted_one(tmp_path, env_id, options):
    run = {"shuffle_agents": True, **TINY, **options}
    algo = run.pop("algo", "mat")
    with Trainer(env_id, algo, out_dir=tmp_path / "a", **run) as straight:
        straight.learn(120, progress_bar=False)
        uninterrupted = finished_state(straight)
    with Trainer(env_id, algo, out_dir=tmp_path / "b", **run) as first:
        first.learn(60, progress_bar=False)
    with Trainer.load(tmp_path / "b" / "checkpoint.pt", out_dir=tmp_path / "b") as resumed:
        assert resumed.progress == checkpoint.Progress(steps=60, updates=2)
        resumed.learn(120, progress_bar=False)
        assert_same_run(uninterrupted, finished_state(resumed), tmp_path / "a", tmp_path / "b")
    assert len(logged_rows(tmp_path / "a")) == 4


def test_one_policy_trains_on_several_agent_counts_of_a_family(tmp_path):
    from mat_export import export

    run = {**TINY, "more_envs": ["swimmer-6"]}
    with Trainer("swimmer-4", "mat", out_dir=tmp_path, **run) as trainer:
        starts = [c.next_obs.copy() for c in trainer.collectors]
        trainer.learn(60, progress_bar=False)  # two updates: one on each count
        assert [c.env.n_agents for c in trainer.collectors] == [3, 5]
        for collector, start in zip(trainer.collectors, starts, strict=True):
            assert not np.array_equal(collector.next_obs, start)  # each count was stepped
    manifest = export(tmp_path / "checkpoint.pt", tmp_path / "onnx", agent_counts=(1, 3))
    assert manifest["agents"]["trained_counts"] == [3, 5]
    on_disk = json.loads((tmp_path / "onnx" / "manifest.json").read_text())
    assert on_disk["agents"]["trained_counts"] == [3, 5]


@pytest.mark.parametrize(
    ("ids", "algo", "problem"),
    [
        (
            ["swimmer-4", "cheetah-6x1"],
            "mat",
            "swimmer-4 gives observations of size|cheetah-6x1 gives observations of size",
        ),
        (["swimmer-4", "swimmer-5"], "mappo", "MAPPO's centralised critic is tied to 3 agents"),
    ],
)
def test_ids_that_cannot_share_a_policy_are_refused(ids, algo, problem):
    with pytest.raises(ValueError, match=problem):
        Trainer(ids[0], algo, more_envs=ids[1:], **TINY)


def test_resume_repairs_a_torn_or_header_only_metrics_file(tmp_path):
    run = {"shuffle_agents": True, **TINY}
    with Trainer("hopper-4x1", "mat", out_dir=tmp_path / "a", **run) as straight:
        straight.learn(120, progress_bar=False)
    with Trainer("hopper-4x1", "mat", out_dir=tmp_path / "b", **run) as first:
        first.learn(60, progress_bar=False)
    metrics = tmp_path / "b" / "metrics.csv"
    metrics.write_text(metrics.read_text() + "90,3,0.1")  # killed mid-row, past the checkpoint
    with Trainer.load(tmp_path / "b" / "checkpoint.pt", out_dir=tmp_path / "b") as resumed:
        resumed.learn(120, progress_bar=False)
    assert logged_rows(tmp_path / "a") == logged_rows(tmp_path / "b")

    header = metrics.read_text().splitlines()[0]
    with Trainer("hopper-4x1", "mat", out_dir=tmp_path / "c", **run) as fresh:
        fresh.learn(30, progress_bar=False)
    (tmp_path / "c" / "metrics.csv").write_text(header + "\n")  # rows lost, header kept
    for total in (60, 90):  # every later resume works, and writes one header
        with Trainer.load(tmp_path / "c" / "checkpoint.pt", out_dir=tmp_path / "c") as again:
            again.learn(total, progress_bar=False)
    lines = (tmp_path / "c" / "metrics.csv").read_text().splitlines()
    assert lines[0] == header and lines.count(header) == 1 and len(lines) == 3


def test_every_generator_is_saved_with_the_device_it_belongs_to(tmp_path):
    with Trainer("hopper-4x1", "mat", **TINY) as trainer:
        rng = trainer.state_payload()["rng"]
    assert rng["device"] == "cpu" and set(rng) == {"torch", "shuffle", "device"}


KILL_OPTIONS = {
    "num_envs": 2,
    "rollout_length": 5,
    "ppo_epochs": 1,
    "num_minibatches": 1,
    "checkpoint_every": 1,
    "env_options": {"episode_limit": 20},
}
KILL_SCRIPT = f"""
import pathlib, sys
from mat_sdk.training.trainer import Trainer
out = pathlib.Path(sys.argv[1])
if (out / "checkpoint.pt").exists():
    trainer = Trainer.load(out / "checkpoint.pt", out_dir=out)
else:
    trainer = Trainer("cheetah-2x3", "mat", out_dir=out, **{KILL_OPTIONS!r})
trainer.learn(10_000_000, progress_bar=False)
"""


@pytest.mark.slow
def test_kill_9_leaves_a_checkpoint_that_resumes_as_if_never_killed(tmp_path):
    script = tmp_path / "train.py"
    script.write_text(KILL_SCRIPT)
    out = tmp_path / "run"
    rng = np.random.default_rng(0)
    progress, last_write = [], 0
    for _ in range(4):
        process = subprocess.Popen(
            [sys.executable, str(script), str(out)], stderr=subprocess.DEVNULL
        )
        deadline = time.time() + 60
        while time.time() < deadline:  # until this process has written at least once
            path = out / "checkpoint.pt"
            if path.exists() and path.stat().st_mtime_ns != last_write:
                break
            time.sleep(0.02)
        time.sleep(rng.uniform(0.0, 0.6))  # then kill it anywhere, mid-write included
        os.kill(process.pid, signal.SIGKILL)
        process.wait()
        payload = checkpoint.load(out / "checkpoint.pt")  # would raise on a torn file
        assert all(torch.isfinite(v).all() for v in payload["model"].values())
        progress.append(payload["progress"]["updates"])
        last_write = (out / "checkpoint.pt").stat().st_mtime_ns
    assert progress == sorted(progress) and progress[-1] > progress[0]  # each resume went on

    # Killed four times and resumed each time, the run is the one that was never killed.
    total = (progress[-1] + 3) * KILL_OPTIONS["num_envs"] * KILL_OPTIONS["rollout_length"]
    with Trainer.load(out / "checkpoint.pt", out_dir=out) as resumed:
        resumed.learn(total, progress_bar=False)
        killed = finished_state(resumed)
    straight_dir = tmp_path / "straight"
    with Trainer("cheetah-2x3", "mat", out_dir=straight_dir, **KILL_OPTIONS) as straight:
        straight.learn(total, progress_bar=False)
        assert_same_run(finished_state(straight), killed, straight_dir, out)


def test_non_finite_loss_stops_training_and_keeps_the_last_good_checkpoint(tmp_path):
    def poison(trainer, metrics):
        if metrics["updates"] == 2:
            with torch.no_grad():
                next(trainer.policy.parameters()).fill_(float("nan"))

    with (
        Trainer(
            "coordination-3", "mat", out_dir=tmp_path, **{**GAME, "checkpoint_every": 1}
        ) as trainer,
        pytest.raises(TrainingDiverged, match="non-finite loss at update 3"),
    ):
        trainer.learn(10_000, progress_bar=False, callback=poison)
    payload = checkpoint.load(tmp_path / "checkpoint.pt")
    assert payload["progress"]["updates"] == 2
    assert all(torch.isfinite(v).all() for v in payload["model"].values())


def test_bad_input_gives_clear_errors(tmp_path):
    with pytest.raises(ValueError, match="unknown algo 'ppo'; valid: mat, mat-dec, mappo, happo"):
        Trainer("coordination-3", "ppo", num_envs=1)
    with pytest.raises(ValueError, match="unknown environment id"):
        Trainer("cheetah-9x9", "mat", num_envs=1)
    with pytest.raises(ValueError, match="unknown training option"):
        Trainer("coordination-3", "mat", learning_rate=1.0)
    with pytest.raises(ValueError, match="recipe must be one of paper, fast, got 'slow'"):
        Trainer("coordination-3", "mat", recipe="slow")
    with pytest.raises(ValueError, match="rollout_backend must be one of torch, onnx, got 'jax'"):
        Trainer("coordination-3", "mat", rollout_backend="jax")  # refused before envs start
    for option, message in (
        ({"num_minibatches": 0}, "num_minibatches must be an integer > 0, got 0"),
        ({"rollout_length": 2.5}, "rollout_length must be an integer > 0, got 2.5"),
        ({"gamma": 1.5}, r"gamma must be a number in \[0, 1\], got 1.5"),
        ({"lr": float("nan")}, "lr must be a number > 0, got nan"),
        ({"lr": "1e-4"}, "lr must be a number > 0, got '1e-4'"),
        ({"device": "tpu"}, "device must be cpu, cuda, cuda:N or auto, got 'tpu'"),
        ({"attention_window": 1}, "attention_window must be an integer >= 2 or null, got 1"),
        ({"attention_window": 4.5}, "attention_window must be an integer >= 2 or null, got 4.5"),
        ({"recipe": "quick"}, "recipe must be one of paper, fast, got 'quick'"),
    ):
        with pytest.raises(ValueError, match=message):
            TrainConfig.from_options(option)
    # numpy scalars are fine, and become Python numbers (weights_only loads)
    accepted = TrainConfig.from_options({"seed": np.int64(3), "lr": np.float32(1e-4)})
    assert type(accepted.run.seed) is int and type(accepted.ppo.lr) is float
    with pytest.raises(ValueError, match="num_minibatches 40 > env-steps per update 10"):
        Trainer("coordination-3", "mat", recipe="paper", num_envs=2, rollout_length=5)
    not_a_checkpoint = tmp_path / "notes.pt"
    not_a_checkpoint.write_text("hello")
    with pytest.raises(checkpoint.CheckpointError, match="is not a MAT checkpoint .not a torch"):
        Trainer.load(not_a_checkpoint)
    pickled_object = tmp_path / "object.pt"
    torch.save({"format": "mat-checkpoint", "path": tmp_path}, pickled_object)
    with pytest.raises(
        checkpoint.CheckpointError, match="weights-only torch.load refused"
    ) as refused:
        Trainer.load(pickled_object)
    assert "\n" not in str(refused.value) and "Re-running" not in str(refused.value)
    with pytest.raises(checkpoint.CheckpointError, match="no checkpoint at"):
        Trainer.load(tmp_path / "missing.pt")
    newer = tmp_path / "newer.pt"
    torch.save({"format": "mat-checkpoint", "version": 99}, newer)
    with pytest.raises(checkpoint.CheckpointError, match="version 99, newer"):
        Trainer.load(newer)


def test_every_algo_trains_saves_loads_and_predicts(tmp_path):
    for algo in ("mat", "mat-dec", "mappo", "happo"):
        with Trainer("hopper-2x2", algo, **TINY) as trainer:
            trainer.learn(30, progress_bar=False)
            path = trainer.save(tmp_path / f"{algo}.pt")
            obs = np.random.default_rng(0).normal(size=(2, trainer.env.obs_dim)).astype(np.float32)
            expected = trainer.predict(obs)
        with Trainer.load(path) as loaded:
            assert np.array_equal(loaded.predict(obs), expected)
            assert loaded.predict(obs[None]).shape == (1, 2, 2)


@pytest.mark.parametrize("env_id", ["humanoid-limbs", "coordination-3"])
def test_predict_takes_and_gives_pettingzoo_dicts(env_id):
    """obs dict in, an action dict `env.step` accepts out: each agent's own action size
    (humanoid pads arms to the legs' 6), or an int choice."""
    env = envs.make(env_id, seed=0)
    obs, _ = env.reset(seed=0)
    options = {k: v for k, v in TINY.items() if env_id != "coordination-3" or k != "env_options"}
    with Trainer(env_id, "mat", **options) as trainer:
        actions = trainer.predict(obs)
        by_array = trainer.predict(np.stack([obs[agent] for agent in env.agents]))
        with pytest.raises(ValueError, match="one entry per agent"):
            trainer.predict({agent: obs[agent] for agent in env.agents[1:]})
    assert list(actions) == env.agents
    for row, agent in enumerate(env.agents):
        assert env.action_space(agent).contains(actions[agent])
        np.testing.assert_array_equal(
            np.ravel(actions[agent]), by_array[row, : np.size(actions[agent])]
        )
    env.step(actions)


def test_progress_bar_counts_whole_updates(capsys):
    """40 steps asked, 30 per update: the run does 60 and its bar ends full at 60/60."""
    with Trainer("hopper-2x2", "mat", **TINY) as trainer:
        trainer.learn(40)
        assert trainer.progress.steps == 60
    bar = capsys.readouterr().err
    assert "60/60" in bar and "/40" not in bar


def test_progress_bar_shows_the_latest_finished_return_not_nan(capsys):
    # per update (10 steps of each env): the mean return, nan if none ended
    with Trainer(
        "hopper-4x1",
        "mat",
        num_envs=2,
        rollout_length=10,
        ppo_epochs=1,
        num_minibatches=1,
        env_options={"episode_limit": 25},
    ) as trainer:
        metrics = []
        trainer.learn(80, callback=lambda _, m: metrics.append(m))
    finished = [m["return_mean"] for m in metrics]
    assert np.isnan(finished).tolist() == [True, True, False, True]  # episodes end at step 25
    bar = capsys.readouterr().err
    shown = re.findall(r"ret=([^,\]]*)", bar)
    assert shown[0] == "-" and "nan" not in shown
    latest = [r for r in finished if not np.isnan(r)][-1]
    assert shown[-1] == f"{latest:.1f}"  # held through the updates where none ended
    shown_rewards = re.findall(r"rew=([^,\]]*)", bar)  # every update, from the first
    per_step = [f"{m['reward_per_step']:.3g}" for m in metrics]
    assert list(dict.fromkeys(shown_rewards)) == list(dict.fromkeys(per_step))
    assert 0 < max(m["reward_per_step"] for m in metrics) <= 1  # dm_control rewards: 0..1


def test_recipes_set_the_update_and_are_recorded(tmp_path):
    """`fast` (the default) and `paper` set the update's shape; options override either; the
    checkpoint records the recipe, and one from before recipes resumes as the paper's."""
    fast, paper = TrainConfig.for_algo("mat"), TrainConfig.for_algo("mat", "paper")
    assert fast == TrainConfig()  # one default: the "fast" recipe
    for config, shape in ((fast, ("fast", 3e-4, 5, 4)), (paper, ("paper", 5e-5, 10, 40))):
        ppo = config.ppo
        assert (config.recipe, ppo.lr, ppo.ppo_epochs, ppo.num_minibatches) == shape
    assert TrainConfig.for_algo("mat", "fast", lr=1e-3).ppo.lr == 1e-3
    mappo = TrainConfig.for_algo("mappo", "fast").ppo  # not measured yet: the paper's settings
    assert (mappo.lr, mappo.critic_lr, mappo.num_minibatches) == (5e-6, 5e-3, 40)
    with Trainer("coordination-3", "mat", num_envs=4, rollout_length=5) as trainer:
        trainer.learn(20, progress_bar=False)
        saved = trainer.save(tmp_path / "fast.pt")
    assert checkpoint.load(saved)["config"]["train"]["recipe"] == "fast"
    old = checkpoint.load(DATA / "mat-coordination3-5510455.pt")
    assert "recipe" not in old["config"]["train"]  # written before recipes existed
    with Trainer.load(DATA / "mat-coordination3-5510455.pt") as resumed:
        assert resumed.config.recipe == "paper"
        assert resumed.config.ppo.lr == old["config"]["train"]["lr"]  # the flat layout


def test_happo_updates_agents_in_turn_each_weighing_the_earlier_agents_new_ratios():
    """One HAPPO update (1 epoch, 1 minibatch) against the algorithm written out by hand:
    critic step, then the agents in the drawn order, each with its own Adam and the advantage
    times the product of the earlier agents' new/old ratios. Fails if the factor is dropped,
    if an agent's step moves another's weights, or if the order is not the drawn one."""
    import copy

    from mat_sdk.training import happo
    from mat_sdk.training.ppo import value_loss

    options = {**TINY, "ppo_epochs": 1, "num_minibatches": 1, "lr": 3e-2, "critic_lr": 1e-2}
    with Trainer("hopper-4x1", "happo", **options) as trainer:
        cfg, policy = trainer.config.ppo, trainer.policy
        rows = trainer.rollout().rows(cfg.advantage_std_floor)
        reference, value_norm = copy.deepcopy(policy), copy.deepcopy(trainer.value_norm)
        generator = torch.Generator().set_state(trainer.collector.shuffle_generator.get_state())
        happo.update(
            policy, trainer.params, trainer.optimizer, trainer.value_norm, rows, cfg,
            trainer.collector.shuffle_generator,
        )  # fmt: skip

    def adam_step(module, loss, lr):
        optimizer = torch.optim.Adam(module.parameters(), lr=lr, eps=cfg.adam_eps)
        module.zero_grad()
        loss.backward()
        torch.nn.utils.clip_grad_norm_(module.parameters(), cfg.max_grad_norm)
        optimizer.step()

    size = len(rows)
    torch.randperm(size, generator=generator)  # the critic's minibatch order
    value_norm.update(rows.returns)
    loss = value_loss(
        reference.values(rows.obs), rows.values, value_norm.normalize(rows.returns),
        cfg.clip, cfg.huber_delta,
    )  # fmt: skip
    adam_step(reference.critic, loss, cfg.critic_lr)
    factor = torch.ones(size, 1)
    order = torch.randperm(4, generator=generator).tolist()
    assert sorted(order) == [0, 1, 2, 3]
    for agent in order:
        torch.randperm(size, generator=generator)  # this agent's minibatch order
        log_prob, entropy = reference.agent_log_prob(agent, rows.obs, rows.actions)
        ratio = torch.exp((log_prob - rows.log_probs[:, agent]).sum(-1, keepdim=True))
        advantages = factor * rows.advantages[:, agent]
        clipped = ratio.clamp(1 - cfg.clip, 1 + cfg.clip)
        surrogate = torch.min(ratio * advantages, clipped * advantages).mean()
        adam_step(reference.actors[agent], -surrogate - cfg.entropy_coef * entropy.mean(), cfg.lr)
        with torch.no_grad():
            log_prob, _ = reference.agent_log_prob(agent, rows.obs, rows.actions)
            factor = factor * torch.exp((log_prob - rows.log_probs[:, agent]).sum(-1, True))
    assert not torch.allclose(factor, torch.ones_like(factor))  # the weighting is exercised
    for (name, ours), theirs in zip(
        policy.state_dict().items(), reference.state_dict().values(), strict=True
    ):
        assert torch.allclose(ours, theirs, atol=1e-5), name


def test_training_episodes_end_at_train_episode_limit_and_evaluations_keep_the_envs(tmp_path):
    """Shorter episodes in training only: more starts per env step; evaluations still run
    the env's own length. (A swimmer never ends an episode early.)"""
    options = {**TINY, "env_options": {"episode_limit": 40}, "train_episode_limit": 10}
    with Trainer("swimmer-4", "mat", out_dir=tmp_path, **options) as trainer:
        trainer.learn(60, progress_bar=False)  # 3 copies x 20 steps: two episodes each
    assert sum(int(row["episodes"]) for row in logged_rows(tmp_path)) == 6
    loaded = CheckpointPolicy.from_checkpoint(tmp_path / "checkpoint.pt")
    assert loaded.training.env.train_episode_limit == 10  # recorded: a resume keeps it
    assert evaluate_episodes(loaded, 2).lengths == [40, 40]  # the env's own limit
    with pytest.raises(ValueError, match="train_episode_limit must be an integer > 0, got 0"):
        Trainer("swimmer-4", "mat", out_dir=tmp_path / "bad", train_episode_limit=0)
