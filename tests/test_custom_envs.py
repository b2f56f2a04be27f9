"""Your own envs: a custom MJCF robot, any dm_control task, any PettingZoo ParallelEnv."""

from __future__ import annotations

import dataclasses
import functools
import json
import os
import re
import subprocess
import sys
from pathlib import Path
from typing import ClassVar

import numpy as np
import pytest
import torch
from gymnasium import spaces
from pettingzoo import ParallelEnv
from pettingzoo.test import parallel_api_test

from mat_sdk import envs
from mat_sdk.training.ppo import LossCoefficients, minibatch_loss, ppo_loss
from mat_sdk.training.trainer import Trainer
from tests import recipes

recipes.with_examples()
import my_robots  # noqa: E402  (examples/, put on the path just above)

ARM_XML = my_robots.MODEL.read_text()
REPO = Path(__file__).resolve().parents[1]
TUTORIAL = REPO / "docs" / "CUSTOM_ENVS.md"


# ------------------------------------------------------------------ a hand-written env
class Uneven(ParallelEnv):
    """Three agents with different observation and action sizes; `c` leaves at step 2.

    Observations: the step count and the agent's last action, padded with constants.
    Reward: minus the squared distance of every acting agent's first action from 0.5.
    """

    metadata: ClassVar[dict] = {"name": "uneven", "render_fps": 10}
    OBS: ClassVar[dict] = {"a": 3, "b": 5, "c": 2}
    ACT: ClassVar[dict] = {"a": 1, "b": 3, "c": 2}

    def __init__(self, seed=None, discrete=False, leave_at=2, length=5):
        self.possible_agents = list(self.OBS)
        self.discrete, self.leave_at, self.length = discrete, leave_at, length
        self._rng = np.random.default_rng(seed)
        self._spaces = {}  # PettingZoo wants the same space object on every call

    def observation_space(self, agent):
        return self._spaces.setdefault(("obs", agent), self.make_observation_space(agent))

    def action_space(self, agent):
        return self._spaces.setdefault(("act", agent), self.make_action_space(agent))

    def make_observation_space(self, agent):
        return spaces.Box(-np.inf, np.inf, (self.OBS[agent],), np.float32)

    def make_action_space(self, agent):
        if self.discrete:
            return spaces.Discrete(self.ACT[agent] + 1)
        return spaces.Box(-1.0, 1.0, (self.ACT[agent],), np.float32)

    def _obs(self, agent, last):
        obs = np.full(self.OBS[agent], self._noise, np.float32)
        obs[0] = self.t
        obs[1 % self.OBS[agent]] = last
        return obs

    def reset(self, seed=None, options=None):
        if seed is not None:
            self._rng = np.random.default_rng(seed)
        self.t, self._noise = 0, float(self._rng.normal())
        self.agents = list(self.possible_agents)
        return {a: self._obs(a, 0.0) for a in self.agents}, {a: {} for a in self.agents}

    def step(self, actions):
        self.t += 1
        first = {a: float(np.asarray(actions[a]).reshape(-1)[0]) for a in self.agents}
        rewards = {a: -((first[a] - 0.5) ** 2) for a in self.agents}
        over = self.t >= self.length
        terminations = {a: a == "c" and self.t >= self.leave_at for a in self.agents}
        truncations = dict.fromkeys(self.agents, over)
        obs = {a: self._obs(a, first[a]) for a in self.agents}
        infos = {a: {} for a in self.agents}
        self.agents = [a for a in self.agents if not (terminations[a] or truncations[a])]
        return obs, rewards, terminations, truncations, infos


def uneven(seed=None):
    return Uneven(seed)


def uneven_discrete(seed=None):
    return Uneven(seed, discrete=True)


def test_uneven_env_is_a_valid_parallel_env():
    parallel_api_test(Uneven(0), num_cycles=20)


def test_different_spaces_are_padded_and_a_leaving_agent_is_masked():
    team = envs.from_pettingzoo(uneven).build(seed=0)
    assert (team.obs_dim, team.action_width, list(team.action_widths)) == (5 + 3, 3, [1, 3, 2])
    obs = team.reset()
    assert obs.shape == (3, 8) and np.all(obs[0, 3:5] == 0)  # a's 3 values, then padding
    assert np.array_equal(obs[:, 5:], np.eye(3))  # one-hot ids after the padding
    actions = np.zeros((3, 3))
    team.step(actions)
    assert team.active.tolist() == [1, 1, 1]
    obs, _, terminated, truncated = team.step(actions)  # c terminates here and leaves
    assert team.active.tolist() == [1, 1, 0] and not (terminated or truncated)
    assert np.all(obs[2] == 0)  # a gone agent's row is zeroed
    for _ in range(3):
        obs, _, terminated, truncated = team.step(actions)
    assert truncated and not terminated  # the rest were cut by the time limit


def test_discrete_agents_with_fewer_choices_get_an_available_mask():
    team = envs.from_pettingzoo(uneven_discrete).build(seed=0)
    team.reset()
    assert team.action_type == "discrete" and team.action_size == 4  # b: 3 + 1 choices
    assert team.available.tolist() == [[1, 1, 0, 0], [1, 1, 1, 1], [1, 1, 1, 0]]


class _Masked(Uneven):
    """Discrete agents whose `action_mask` arrives in the observation dict."""

    def __init__(self, seed=None):
        super().__init__(seed, discrete=True)

    def make_observation_space(self, agent):
        n = self.ACT[agent] + 1
        box = super().make_observation_space(agent)
        return spaces.Dict({"observation": box, "action_mask": spaces.MultiBinary(n)})

    def _obs(self, agent, last):
        mask = np.zeros(self.ACT[agent] + 1, np.int8)
        mask[-1] = 1  # only the last choice is allowed
        return {"observation": super()._obs(agent, last), "action_mask": mask}


def masked(seed=None):
    return _Masked(seed)


class _MaskedInInfos(Uneven):
    """Discrete agents whose `action_mask` arrives in their infos."""

    def __init__(self, seed=None):
        super().__init__(seed, discrete=True)

    def _with_masks(self, infos):
        for agent in infos:
            infos[agent]["action_mask"] = np.eye(self.ACT[agent] + 1, dtype=np.int8)[-1]
        return infos

    def reset(self, seed=None, options=None):
        obs, infos = super().reset(seed, options)
        return obs, self._with_masks(infos)

    def step(self, actions):
        *rest, infos = super().step(actions)
        return (*rest, self._with_masks(infos))


def masked_in_infos(seed=None):
    return _MaskedInInfos(seed)


@pytest.mark.parametrize("factory", [masked, masked_in_infos], ids=["in obs", "in infos"])
def test_action_masks_reach_the_policy(factory):
    spec = envs.from_pettingzoo(factory)
    with Trainer(spec, "mat", num_envs=4, rollout_length=5, num_minibatches=1) as trainer:
        trajectory = trainer.rollout()
        rows = trajectory.rows()
        log_prob, _, _ = trainer.policy.evaluate_actions(rows.obs, rows.actions, rows.available)
    chosen = trajectory.actions[..., 0]  # [T, E, n]
    active = trajectory.active[..., 0] > 0
    last_choice = torch.tensor([1.0, 3.0, 2.0]).expand_as(chosen)
    assert torch.equal(chosen[active], last_choice[active])  # never a masked-out choice
    assert torch.all(log_prob[rows.active[..., 0] > 0] == 0)  # the loss sees one choice


def test_predict_takes_available_actions():
    with Trainer(envs.from_pettingzoo(uneven_discrete), "mat", num_envs=2, rollout_length=5) as t:
        obs = t.env.reset()[0]
        only_first = np.zeros((3, 4))
        only_first[:, 0] = 1
        assert t.predict(obs, available=only_first)[:, 0].tolist() == [0, 0, 0]
        only_last = np.eye(4)[[1, 3, 2]]  # each agent's last own choice
        assert t.predict(obs, available=only_last)[:, 0].tolist() == [1, 3, 2]


def test_a_custom_robot_steps_in_env_worker_processes():
    """Workers rebuild the env from the pickled spec: its reward is importable."""
    with (
        envs.make_vec("my_robots:arm", 2, workers=1, seed=0) as vec,
        envs.make_vec("my_robots:arm", 2, seed=0) as local,
    ):
        actions = np.full((2, 2, 2), 0.3)
        assert np.array_equal(vec.reset(), local.reset())
        assert np.array_equal(vec.step(actions)[0], local.step(actions)[0])


def _uneven_batch():
    with Trainer(envs.from_pettingzoo(uneven), "mat", num_envs=4, rollout_length=10) as trainer:
        return trainer, trainer.rollout().rows()


def test_padded_dimensions_and_gone_agents_get_exactly_zero_gradient():
    trainer, rows = _uneven_batch()
    assert rows.active is not None and rows.action_dims is not None
    inactive = rows.active[..., 0] == 0
    assert inactive[:, 2].any() and not inactive[:, :2].any()  # only c ever leaves
    log_prob, entropy, values = trainer.policy.evaluate_actions(rows.obs, rows.actions)
    log_prob, entropy, values = (x.detach().requires_grad_() for x in (log_prob, entropy, values))
    terms = ppo_loss(
        log_prob, rows.log_probs, rows.advantages, entropy, values, rows.values,
        rows.returns, 0.2, 0.01, 1.0, 10.0, rows.active, rows.action_dims,
    )  # fmt: skip
    terms.total.backward()
    padded = rows.action_dims == 0
    assert padded.any()
    for grad in (log_prob.grad, entropy.grad):
        assert torch.all(grad[padded] == 0)  # padding: exactly zero
        assert torch.all(grad[inactive] == 0)  # a gone agent's rows: exactly zero
        assert torch.all(grad[~padded & ~inactive[..., None].expand_as(padded)] != 0)
    assert torch.all(values.grad[inactive] == 0) and torch.any(values.grad[~inactive] != 0)


def test_a_gone_agents_rows_change_nothing_in_the_loss():
    trainer, rows = _uneven_batch()
    coefficients = LossCoefficients.of(trainer.config.ppo)

    def loss_and_gradient(batch):
        trainer.policy.zero_grad()
        terms = minibatch_loss(trainer.policy, batch, batch.returns, coefficients)
        terms.total.backward()
        grads = [p.grad.clone() for p in trainer.policy.parameters() if p.grad is not None]
        return terms.total.detach(), grads

    base_loss, base_grads = loss_and_gradient(rows)
    gone = rows.active == 0
    changed = {
        key: torch.where(gone, torch.randn_like(getattr(rows, key)) * 100, getattr(rows, key))
        for key in ("advantages", "returns", "values")
    }
    changed["log_probs"] = torch.where(gone, rows.log_probs - 5, rows.log_probs)
    loss, grads = loss_and_gradient(dataclasses.replace(rows, **changed))
    assert torch.equal(loss, base_loss)
    assert all(torch.equal(g, h) for g, h in zip(grads, base_grads, strict=True))


def test_an_unfinished_episode_resumes_exactly_by_replay():
    vec = envs.make_vec(envs.from_pettingzoo(uneven), 2, seed=3)
    vec.reset(seed=3)
    rng = np.random.default_rng(0)
    for _ in range(3):
        vec.step(rng.uniform(-1, 1, (2, 3, 3)))
    state = vec.get_state()
    actions = rng.uniform(-1, 1, (4, 2, 3, 3))
    first = [vec.step(a)[:2] for a in actions]
    vec.set_state(state)
    again = [vec.step(a)[:2] for a in actions]
    for (obs, reward), (obs2, reward2) in zip(first, again, strict=True):
        assert np.array_equal(obs, obs2) and np.array_equal(reward, reward2)
    vec.close()


class _Odd(Uneven):
    def __init__(self, seed=None, kind="dict"):
        super().__init__(seed)
        self.kind = kind

    def make_observation_space(self, agent):
        if self.kind == "dict":
            return spaces.Dict({"pos": spaces.Box(-1, 1, (2,))})
        return super().make_observation_space(agent)

    def make_action_space(self, agent):
        if self.kind == "multidiscrete":
            return spaces.MultiDiscrete([2, 3])
        if self.kind == "mixed" and agent == "a":
            return spaces.Discrete(2)
        return super().make_action_space(agent)


@pytest.mark.parametrize(
    ("kind", "named"),
    [("dict", "observation space Dict"), ("multidiscrete", "MultiDiscrete"), ("mixed", "Box")],
)
def test_unsupported_spaces_say_what_is_supported(kind, named):
    with pytest.raises(ValueError, match="not supported; supported: every agent") as error:
        envs.from_pettingzoo(functools.partial(_Odd, kind=kind))
    assert named in str(error.value)


# ------------------------------------------------------------------ your own MuJoCo robot
def reward_nothing(physics) -> float:
    return 0.0


@pytest.mark.parametrize(
    ("layout", "problem"),
    [
        ([["shoulder"], ["hip"]], "no actuator named 'hip'; its actuators: shoulder, elbow, wrist"),
        ([["shoulder", "elbow"], ["elbow"]], "actuator 'elbow' is in two agents"),
        ([["shoulder"], []], "agent 1 of the layout drives no actuator"),
        ({"arm": "shoulder"}, "must be a list of names, got the string 'shoulder'"),
    ],
)
def test_layout_mistakes_name_the_problem(layout, problem):
    with pytest.raises(ValueError, match=problem):
        envs.from_mjcf(ARM_XML, layout, reward_nothing)


def test_a_model_without_actuators_is_refused():
    bare = ARM_XML.split("<actuator>")[0] + "</mujoco>"
    with pytest.raises(ValueError, match="the model has no actuators"):
        envs.from_mjcf(bare, [["shoulder"]], reward_nothing)


def test_a_missing_model_file_is_refused(tmp_path):
    with pytest.raises(ValueError, match="neither an MJCF file nor an XML string"):
        envs.from_mjcf(tmp_path / "robot.xml", [["shoulder"]], reward_nothing)


def test_the_custom_arm_is_decomposed_like_a_built_in_robot():
    team = envs.make_team("my_robots:arm", seed=0)
    assert team.env_id == "my_robots:arm" and team.agents == ["shoulder", "forearm"]
    assert list(team.action_widths) == [1, 2]
    assert team.joint_names(1) == ["elbow", "wrist"]
    assert team.control_timestep == pytest.approx(0.02)  # the model's 0.01 s x 2 substeps
    parallel_api_test(envs.make("my_robots:arm"), num_cycles=60)
    broken = envs.make_team("my_robots:arm", faults={"wrist": "zero"}, seed=0)
    assert broken.n_agents == 2
    fewer = envs.make_team("my_robots:arm", faults={"forearm": "remove"})
    assert fewer.agents == ["shoulder"]


def test_a_dm_control_suite_task_with_a_layout_of_its_own():
    from mat_sdk.envs.mujoco.robots import SuiteTask

    with pytest.warns(
        envs.UnusedActuators,
        match=r"leaves actuators \['bshin', 'bfoot', 'fshin', 'ffoot'\]",
    ):
        spec = envs.from_dm_control(
            SuiteTask("cheetah", "run"), {"back": ["bthigh"], "front": ["fthigh"]}
        )
    team = spec.build(seed=0)
    assert team.agents == ["back", "front"] and team.episode_limit == 1000
    obs, reward, *_ = team.step(np.zeros((2, 1)))
    assert obs.shape == (2, team.obs_dim) and np.isfinite(reward)


def test_trainer_takes_a_spec_and_a_module_level_factory():
    with Trainer(my_robots.arm(), "mat", num_envs=2, rollout_length=4, num_minibatches=1) as t:
        assert t.config.env.id == "mjcf:arm"
    with Trainer(my_robots.arm, "mat", num_envs=2, rollout_length=4, num_minibatches=1) as t:
        assert t.config.env.id == "my_robots:arm"  # rebuildable in any process
        t.learn(8, progress_bar=False)


@pytest.mark.parametrize(
    ("env_id", "problem"),
    [
        ("no_such_module:arm", "no module 'no_such_module' to import"),
        ("my_robots:no_such_function", "module 'my_robots' has no 'no_such_function'"),
        ("my_robots:reach_reward", "must name a function of no arguments"),
    ],
)
def test_a_module_function_id_that_cannot_be_found_names_what_was_looked_for(env_id, problem):
    with pytest.raises(ValueError, match=problem):
        envs.make_team(env_id)


# ------------------------------------------------------------------ learning
def test_mat_learns_the_custom_arm():
    assert recipes.arm_return(0) >= recipes.beats_random(recipes.ARM_ENV, recipes.ARM_FRACTION)


@pytest.mark.slow
def test_mat_learns_mpe_simple_spread():
    score = recipes.spread_return(0, "mpe_envs:spread")
    assert score >= recipes.beats_random("mpe_envs:spread", recipes.SPREAD_FRACTION)


@pytest.mark.slow
def test_mat_learns_mpe_simple_spread_with_continuous_actions():
    env_id = "mpe_envs:spread_continuous"
    score = recipes.spread_return(0, env_id, recipes.SPREAD_CONTINUOUS_STEPS)
    assert score >= recipes.beats_random(env_id, recipes.SPREAD_CONTINUOUS_FRACTION)


@pytest.mark.parametrize("env_id", ["mpe_envs:spread", "mpe_envs:spread_continuous"])
def test_pettingzoo_actions_train_end_to_end(env_id):
    """Both action kinds of MPE in seconds (the learning claims are the slow tests above:
    32,000 and 96,000 steps, 40 s and more)."""
    with Trainer(env_id, "mat", num_envs=4, rollout_length=25) as trainer:
        trainer.learn(200, progress_bar=False)
        trajectory = trainer.rollout()
        returns = trainer.evaluate(2)
    assert trajectory.action_dims is None and torch.all(trajectory.active == 1)
    assert (trajectory.available is not None) == (trainer.env.action_type == "discrete")
    assert len(returns) == 2 and all(np.isfinite(returns))


# ------------------------------------------------------------------ the tools, by env id
def _blocks(kind: str) -> list[str]:
    return re.findall(rf"```{kind}\n(.*?)```", TUTORIAL.read_text(), flags=re.S)


def _tutorial_commands() -> list[str]:
    lines = [line for block in _blocks("bash") for line in block.splitlines()]
    return [line for line in lines if line and not line.startswith("export PYTHONPATH")]


def _run(command: str, cwd: Path) -> subprocess.CompletedProcess:
    """A tutorial command as a user runs it, from a directory holding `examples/`."""
    words = command.split()
    if words[0] == "mat":
        words = [sys.executable, "-m", "mat_sdk", *words[1:]]
    elif words[0] == "python":
        words = [sys.executable, *words[1:]]
    environment = {**os.environ, "PYTHONPATH": str(cwd / "examples")}
    return subprocess.run(words, cwd=cwd, env=environment, capture_output=True, text=True)


def _workdir(tmp_path: Path) -> Path:
    (tmp_path / "examples").symlink_to(REPO / "examples")
    return tmp_path


def _check_tutorial(tmp_path: Path, shorten: bool) -> dict[str, str]:
    cwd, outputs = _workdir(tmp_path), {}
    commands = _tutorial_commands()
    assert len(commands) == 7
    if shorten:  # the robot's to its export and controller, one update: learning is tested
        # above, by recipe; fine-tuning by its own tests
        commands = [
            re.sub(r"--steps \d+", "--steps 1", c)
            for c in commands
            if "spread" not in c and "finetune" not in c
        ]
    for command in commands:
        done = _run(command, cwd)
        assert done.returncode == 0, f"{command}\n{done.stdout}\n{done.stderr}"
        outputs[command.split()[1] + " " + command.split()[2]] = done.stdout
    manifest = json.loads((cwd / "runs/arm/onnx/manifest.json").read_text())
    assert manifest["env_id"] == "my_robots:arm"
    # the loop reports its timing; how many ticks are late is the machine's load, not the code's
    assert re.search(r"late ticks: \d+;", outputs["examples/controller.py runs/arm/onnx"])
    assert (
        "my_robots:arm with agents ['shoulder', 'forearm']"
        in outputs["examples/controller.py runs/arm/onnx"]
    )
    return outputs


@pytest.mark.slow
def test_every_tutorial_command_runs_with_the_ids_it_names(tmp_path):
    """module:function ids through mat train, eval, export and the controller (subprocesses)."""
    outputs = _check_tutorial(tmp_path, shorten=True)
    assert "over 8 episodes" in outputs["eval runs/arm/checkpoint.pt"]


@pytest.mark.slow
def test_the_tutorial_as_written_trains_an_arm_that_beats_a_random_team(tmp_path):
    outputs = _check_tutorial(tmp_path, shorten=False)
    assert "over 16 episodes" in outputs["eval runs/spread/checkpoint.pt"]
    assert (tmp_path / "runs/arm-no-wrist/checkpoint.pt").is_file()
    found = re.search(r"return (-?[\d.]+) \+-", outputs["eval runs/arm/checkpoint.pt"])
    assert float(found.group(1)) >= recipes.beats_random(recipes.ARM_ENV, recipes.ARM_FRACTION)


def test_the_tutorials_python_runs_and_its_module_is_the_example():
    module, usage, spread = _blocks("python")
    examples = REPO / "examples"
    for block, source in ((module, "my_robots.py"), (spread, "mpe_envs.py")):
        code = (examples / source).read_text()
        assert all(line in code for line in block.splitlines()), source
    exec(compile(usage, str(TUTORIAL), "exec"), {})


def test_a_module_function_id_that_cannot_be_found_is_one_line_from_the_cli(tmp_path):
    done = _run("mat train no_such_module:arm --steps 1", _workdir(tmp_path))
    assert done.returncode != 0
    assert done.stderr.strip().count("\n") == 0 and "Traceback" not in done.stderr
    assert "no module 'no_such_module' to import" in done.stderr


def test_an_installed_package_registers_ids_that_mat_envs_lists(tmp_path):
    """A distribution with a `mat_sdk.envs` entry point, as `pip install` leaves it."""
    info = tmp_path / "my_robots_pkg-1.0.dist-info"
    info.mkdir()
    (info / "METADATA").write_text("Metadata-Version: 2.1\nName: my-robots-pkg\nVersion: 1.0\n")
    (info / "entry_points.txt").write_text("[mat_sdk.envs]\narm-2 = my_robots:arm\n")
    environment = {**os.environ, "PYTHONPATH": f"{tmp_path}{os.pathsep}{REPO / 'examples'}"}
    listed = subprocess.run(
        [sys.executable, "-m", "mat_sdk", "envs"], env=environment, capture_output=True, text=True
    )
    assert listed.returncode == 0, listed.stderr
    rows = {line.split()[0]: line.split()[1:] for line in listed.stdout.splitlines()[3:]}
    assert rows["arm-2"][:3] == ["2", "10", "2"]  # agents, obs size, action size
    families = {name for name, row in rows.items() if "[family]" in row}
    assert families == {
        "swimmer-3", "swimmer-6", "swimmer-15",
        "mamujoco:ManySegmentSwimmer-4x2", "mamujoco:ManySegmentAnt-3x2",
    }  # fmt: skip
    built = subprocess.run(
        [sys.executable, "-c", "from mat_sdk import envs; print(envs.make_team('arm-2').agents)"],
        env=environment, capture_output=True, text=True,
    )  # fmt: skip
    assert built.stdout.strip() == "['shoulder', 'forearm']", built.stderr


def test_a_fixed_base_arms_first_joint_is_observed_through_its_encoder():
    """The shoulder hangs from the world like a floating base, but it is driven: on hardware
    its encoder reads it, so the observation has all seven joints of each arm."""
    team = envs.make_team("bimanual:reach", seed=0)
    team.reset()
    features = {f.name: f.stop - f.start for f in team.wiring().observation.features}
    assert features["joints.pos"] == features["joints.vel"] == 7
    assert team.wiring().observation.signals["joint_pos"][0] == "left_shoulder_pan_joint"
    assert features["sensor.left_hand"] == features["sensor.right_target"] == 3
