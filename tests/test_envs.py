"""Multi-agent robots: PettingZoo API, decomposition, seeding, faults, bad input."""

import math
import os
import re
import signal
import subprocess
import sys
import time

import gymnasium
import mujoco
import numpy as np
import pytest
from pettingzoo.test import parallel_api_test

from mat_sdk import envs
from mat_sdk.common import processes
from mat_sdk.envs.core.vector import TeamFactory, VecTeam
from mat_sdk.envs.mujoco.robots import spec_for
from tests.recipes import with_examples

ROBOT_IDS = [
    "cheetah-6x1",
    "cheetah-2x3",
    "walker-6x1",
    "walker-2x3",
    "hopper-4x1",
    "hopper-2x2",
    "quadruped-4x3",
    "humanoid-limbs",
    "swimmer-3",
    "swimmer-6",
]


@pytest.mark.parametrize("env_id", [*ROBOT_IDS, "coordination-3"])
def test_parallel_api(env_id):
    parallel_api_test(envs.make(env_id, seed=0), num_cycles=40)


def test_mamujoco_parallel_api_and_vector():
    parallel_api_test(envs.make("mamujoco:HalfCheetah-6x1", seed=0), num_cycles=20)
    with envs.make_vec("mamujoco:HalfCheetah-6x1", num_envs=2, seed=0) as vec:
        obs = vec.reset()
        assert obs.shape == (2, 6, 13)  # the paper's 13: own 2 + root 5 + one-hot id 6
        obs, reward, *_ = vec.step(np.zeros((2, 6, 1)))
        assert reward.shape == (2,) and np.isfinite(obs).all()


def _driven_dofs(team, row: int, dim: int) -> set[int]:
    """DOFs that one action entry pushes, read from MuJoCo, not from our decomposition.

    First which actuators the entry moves (their ctrl changes), then which DOFs MuJoCo's
    transmission (the actuator moment) connects those actuators to.
    """
    data, model = team.physics.data, team.physics.model
    ctrls = []
    for value in (-0.7, 0.7):
        team.reset(seed=0)
        actions = np.zeros((team.n_agents, team.action_width))
        actions[row, dim] = value
        team.step(actions)
        ctrls.append(data.ctrl.copy())
    team.reset(seed=0)
    mujoco.mj_forward(model.ptr, data.ptr)  # fills MuJoCo's sparse actuator moments
    dofs = set()
    for actuator in np.flatnonzero(ctrls[0] != ctrls[1]):
        start, count = data.moment_rowadr[actuator], data.moment_rownnz[actuator]
        dofs |= set(data.moment_colind[start : start + count].tolist())
    return dofs


@pytest.mark.parametrize("env_id", ROBOT_IDS)
def test_each_agent_observes_the_joints_it_drives(env_id):
    team = envs.make_team(env_id, seed=0)
    model = team.physics.model
    for row in range(team.n_agents):
        for dim in range(team.action_widths[row]):
            dofs = _driven_dofs(team, row, dim)
            assert dofs, f"{env_id} agent {row} action {dim} drives nothing"
            for dof in dofs:
                team.reset(seed=0)
                before = team.observe()[row].copy()
                joint = model.dof_jntid[dof]
                team.physics.data.qpos[model.jnt_qposadr[joint]] += 0.1
                after_qpos = team.observe()[row].copy()
                team.physics.data.qvel[dof] += 0.3
                after_qvel = team.observe()[row]
                name = model.id2name(joint, "joint")
                assert not np.allclose(before, after_qpos), (
                    f"{env_id}: agent {row} blind to {name} qpos"
                )
                assert not np.allclose(after_qpos, after_qvel), (
                    f"{env_id}: agent {row} blind to {name} qvel"
                )


def test_same_seed_same_episode_and_other_seed_differs():
    def episode(seed):
        env = envs.make("walker-2x3", seed=seed)
        obs, _ = env.reset(seed=seed)
        rng = np.random.default_rng(0)
        trace = [np.concatenate(list(obs.values()))]
        for _ in range(30):
            obs, rewards, *_ = env.step({a: rng.uniform(-1, 1, 3) for a in env.agents})
            trace.append(np.concatenate([*obs.values(), list(rewards.values())]))
        return np.concatenate(trace)

    assert np.array_equal(episode(7), episode(7))
    assert not np.allclose(episode(7), episode(8))


def test_obs_float32_state_and_shared_reward():
    env = envs.make("cheetah-6x1", seed=0)
    obs, _ = env.reset(seed=0)
    assert all(o.dtype == np.float32 and o.shape == (17,) for o in obs.values())
    assert env.state().shape == env.state_space.shape and env.state().dtype == np.float32
    _, rewards, *_ = env.step({a: np.ones(1) for a in env.agents})
    assert len(set(rewards.values())) == 1


def test_one_hot_agent_id_and_swimmer_obs_size_independent_of_n():
    obs, _ = envs.make("hopper-4x1").reset(seed=0)
    ids = np.stack([o[-4:] for o in obs.values()])
    assert np.array_equal(ids, np.eye(4))
    sizes = {envs.make_team(f"swimmer-{n}").obs_dim for n in (3, 4, 7, 12)}
    assert len(sizes) == 1
    assert not envs.make_team("swimmer-5").agent_id  # variable-count family: no one-hot id
    assert envs.make_team("hopper-4x1", agent_id=False).obs_dim == 11


@pytest.mark.parametrize("family", ["swimmer-{}", "mamujoco:ManySegmentSwimmer-{}x2"])
def test_count_independent_positions_keep_one_observation_size(family):
    for position, width in (("fraction", 1), ("ends", 2), ("near-ends", 2), ("end-flags", 2)):
        teams = [envs.make_team(family.format(n), position=position) for n in (4, 7)]
        plain = envs.make_team(family.format(4)).obs_dim
        assert {t.obs_dim for t in teams} == {plain + width}
        features = teams[1].reset(seed=0)[:, -width:]
        count = teams[1].n_agents
        if position == "fraction":
            assert np.allclose(features[:, 0], np.linspace(0, 1, count))
        elif position == "ends":
            assert np.allclose(features[0], [1, 1 / count]) and np.allclose(
                features[-1], [1 / count, 1]
            )
        else:  # counted up to 2 or 1: the inside agents all look alike
            inside = [1, 1] if position == "end-flags" else [0.5, 1]
            assert features[[0, 1, -1]].tolist() == [[0, 1], inside, [1, 0]]
            assert (features[2:-2] == 1).all()
    with pytest.raises(ValueError, match="position must be one of"):
        envs.make_team(family.format(4), position="middle")


@pytest.mark.parametrize(
    ("family", "counts", "size"),
    [("ManySegmentSwimmer", (2, 3, 4, 8), 6), ("ManySegmentAnt", (2, 4), 115)],
)
def test_mamujoco_families_have_one_observation_size_for_every_count(family, counts, size):
    teams = [envs.make_team(f"mamujoco:{family}-{k}x2") for k in counts]
    assert [t.n_agents for t in teams] == list(counts)
    assert {t.obs_dim for t in teams} == {size}  # agent_obsk=1, no one-hot id by default
    assert all(t.variable_count for t in teams)
    assert not envs.make_team("mamujoco:HalfCheetah-6x1").variable_count


def test_padding_to_a_maximum_count_adds_inactive_zero_agents_that_change_nothing():
    plain = envs.make_team("mamujoco:ManySegmentSwimmer-3x2", agent_id=True)
    padded = envs.make_team("mamujoco:ManySegmentSwimmer-3x2", agent_id=True, pad_agents=6)
    assert (padded.n_agents, padded.obs_dim, padded.masks) == (6, 6 + 6, True)
    assert list(padded.active) == [1, 1, 1, 0, 0, 0]
    obs, obs_padded = plain.reset(seed=3), padded.reset(seed=3)
    assert np.array_equal(obs_padded[:3, :5], obs[:, :5])  # own features, then a 6-entry id
    assert np.array_equal(obs_padded[:3, 6:], np.eye(3, 6)) and not obs_padded[3:].any()
    actions = np.random.default_rng(0).uniform(-1, 1, (6, 2))
    step, step_padded = plain.step(actions[:3]), padded.step(actions)  # padding's are dropped
    assert step[1] == step_padded[1] and np.array_equal(step_padded[0][:3, :5], step[0][:, :5])
    vec = envs.make_vec("mamujoco:ManySegmentSwimmer-3x2", 2, pad_agents=5)
    vec.reset(seed=0)
    assert vec.active().tolist() == [[1, 1, 1, 0, 0]] * 2
    with pytest.raises(ValueError, match="pad_agents=2 is fewer than the 3 agents"):
        envs.make_team("mamujoco:ManySegmentSwimmer-3x2", pad_agents=2)


def test_family_envs_build_in_parallel_processes():
    """Gymnasium-Robotics writes a family's model to one fixed file and deletes it after
    loading; processes building the same K at once must not collide."""
    script = (
        "from mat_sdk.envs import make_team\n"
        "for _ in range(8): make_team('mamujoco:ManySegmentSwimmer-4x2')\n"
    )
    runs = [
        subprocess.Popen([sys.executable, "-c", script], stderr=subprocess.PIPE) for _ in range(4)
    ]
    errors = [run.communicate()[1].decode() for run in runs]
    assert [run.returncode for run in runs] == [0] * 4, errors


def test_fast_reward_equals_the_suite_task_reward():
    team = envs.make_team("cheetah-6x1", seed=0)
    team.reset(seed=0)
    rng = np.random.default_rng(0)
    for _ in range(200):
        _, reward, *_ = team.step(rng.uniform(-1, 1, (6, 1)))
        assert reward == pytest.approx(team._task.get_reward(team.physics), abs=1e-12)


def test_truncation_at_configured_episode_limit():
    env = envs.make("hopper-2x2", episode_limit=5)
    env.reset(seed=0)
    for step in range(5):
        _, _, terminated, truncated, _ = env.step({a: np.zeros(2) for a in env.agents})
        assert all(truncated.values()) == (step == 4)
        assert not any(terminated.values())
    assert env.agents == []


@pytest.mark.parametrize(
    ("actions", "message"),
    [
        ({"agent_0": [0.0]}, r"no action for agent\(s\) \['agent_1'"),
        ({**{f"agent_{i}": [0.0] for i in range(6)}, "agent_9": [0.0]}, "unknown agent"),
        (
            {**{f"agent_{i}": [0.0] for i in range(6)}, "agent_3": [0.0, 1.0]},
            r"agent_3: action has shape \(2,\)",
        ),
        (
            {**{f"agent_{i}": [0.0] for i in range(6)}, "agent_2": [np.nan]},
            "agent_2: action contains NaN",
        ),
        (
            {**{f"agent_{i}": [0.0] for i in range(6)}, "agent_4": [np.inf]},
            "agent_4: action contains NaN or inf",
        ),
    ],
)
def test_bad_actions_raise_value_error_naming_the_agent(actions, message):
    env = envs.make("cheetah-6x1")
    env.reset(seed=0)
    with pytest.raises(ValueError, match=message):
        env.step(actions)


@pytest.mark.parametrize("env_id", ["cheetah-6x1", "coordination-3"])
def test_array_team_refuses_bad_actions_and_wrappers_check_once(env_id, monkeypatch):
    team = envs.make_team(env_id, seed=0)
    team.reset(seed=0)
    good = np.zeros((team.n_agents, team.action_width))
    bad = good.copy()
    bad[1, 0] = np.nan
    with pytest.raises(ValueError, match="agent_1: action contains NaN"):
        team.step(bad)
    with pytest.raises(ValueError, match=r"actions have shape \(3,\)"):
        team.step(good[:3, 0])
    calls = []
    check = type(team).check_actions
    monkeypatch.setattr(
        type(team), "check_actions", lambda self, a: calls.append(1) or check(self, a)
    )
    team.step(good)
    assert len(calls) == 1
    env = envs.make(env_id, seed=0)  # checks its per-agent dict, then steps unchecked
    env.reset(seed=0)
    env.step({agent: np.zeros(team.action_width) for agent in env.agents})
    with envs.make_vec(env_id, num_envs=2, seed=0) as vec:  # checks the whole batch
        vec.reset()
        vec.step(np.zeros((2, team.n_agents, team.action_width)))
    assert len(calls) == 1


@pytest.mark.parametrize("choice", [3, -1, 0.5])
def test_discrete_actions_must_be_choices_on_every_path(choice):
    team = envs.make_team("coordination-3", seed=0)
    team.reset(seed=0)
    actions = np.array([[0.0], [choice], [2.0]])
    with pytest.raises(ValueError, match=r"agent_1: action must be a choice 0\.\.2"):
        team.step(actions)
    with envs.make_vec("coordination-3", num_envs=2, seed=0) as vec:
        vec.reset()
        with pytest.raises(ValueError, match=r"env 1, agent_1: action must be a choice 0\.\.2"):
            vec.step(np.stack([np.zeros((3, 1)), actions]))
    env = envs.make("coordination-3", seed=0)
    env.reset(seed=0)
    assert env.action_space("agent_1") == gymnasium.spaces.Discrete(3)
    with pytest.raises(ValueError, match=r"agent_1: action must be a choice 0\.\.2"):
        env.step({"agent_0": 0, "agent_1": choice, "agent_2": 2})
    target = int(env.state().argmax())
    others = [option for option in range(3) if option != target]
    rewards = env.step({"agent_0": target, "agent_1": others[0], "agent_2": np.int64(others[1])})[1]
    assert rewards == dict.fromkeys(["agent_0", "agent_1", "agent_2"], 1.0)


def test_out_of_range_actions_are_clipped():
    results = []
    for value in (1.0, 7.5):
        team = envs.make_team("cheetah-6x1", seed=0)
        team.reset(seed=0)
        results.append(team.step(np.full((6, 1), value))[0])
    assert np.array_equal(results[0], results[1])


def test_unknown_env_id_lists_valid_ids():
    with pytest.raises(
        ValueError, match="unknown environment id 'cheetah-9x9'.*cheetah-6x1.*swimmer-N"
    ):
        envs.make("cheetah-9x9")


def test_zero_fault_silences_the_joint_and_keeps_the_agent():
    team = envs.make_team("cheetah-6x1", faults={"bfoot": "zero"}, seed=0)
    assert team.n_agents == 6
    team.reset(seed=0)
    team.step(np.ones((6, 1)))
    ctrl = team.physics.named.data.ctrl
    assert ctrl["bfoot"] == 0.0 and ctrl["bshin"] == 1.0


def test_remove_fault_drops_the_agent_and_keeps_names_and_ids():
    full = envs.make_team("cheetah-6x1")
    team = envs.make_team("cheetah-6x1", faults={"agent_2": "remove"}, seed=0)
    assert team.n_agents == 5 and team.agents == [
        "agent_0",
        "agent_1",
        "agent_3",
        "agent_4",
        "agent_5",
    ]
    assert team.obs_dim == full.obs_dim
    obs = team.reset(seed=0)
    assert np.array_equal(obs[:, -6:], np.eye(6)[[0, 1, 3, 4, 5]])
    team.step(np.ones((5, 1)))
    assert team.physics.named.data.ctrl["bfoot"] == 0.0
    by_joint = envs.make_team("cheetah-6x1", faults={"bfoot": "remove"})
    assert by_joint.agents == team.agents


def test_bad_faults_are_rejected_clearly():
    with pytest.raises(ValueError, match="neither an agent nor an actuated joint.*bfoot"):
        envs.make("cheetah-6x1", faults={"tail": "zero"})
    with pytest.raises(ValueError, match="mode must be one of"):
        envs.make("cheetah-6x1", faults={"bfoot": "wobble"})
    with pytest.raises(ValueError, match="remove every agent"):
        envs.make("cheetah-2x3", faults={"agent_0": "remove", "agent_1": "remove"})


def test_mamujoco_travel_is_the_root_x_the_forward_reward_pays_for():
    """A Walker's travel is its root's x displacement this episode; a Reacher has no moving
    root, so no travel."""
    team = envs.make_team("mamujoco:Walker2d-2x3", seed=0)
    team.reset(seed=0)
    env = team._env.single_agent_env.unwrapped
    start = float(env.data.qpos[0])
    for _ in range(20):
        team.step(np.full((2, 3), 0.5))
    assert team.travelled() == pytest.approx(float(env.data.qpos[0]) - start)
    assert abs(team.travelled()) > 1e-3
    reacher = envs.make_team("mamujoco:Reacher-2x1", seed=0)
    reacher.reset(seed=0)
    reacher.step(np.full((2, 1), 0.5))
    assert math.isnan(reacher.travelled())


def test_mamujoco_faults_name_an_agent_or_a_joint():
    def ctrl_after_full_push(faults):
        team = envs.make_team("mamujoco:HalfCheetah-6x1", faults=faults, seed=0)
        team.reset(seed=0)
        team.step(np.ones((6, 1)))
        return team._env.single_agent_env.unwrapped.data.ctrl.copy()

    assert ctrl_after_full_push({}).tolist() == [1.0] * 6
    by_joint = ctrl_after_full_push({"bfoot": "zero"})  # actuators: bthigh bshin bfoot ...
    assert by_joint.tolist() == [1.0, 1.0, 0.0, 1.0, 1.0, 1.0]
    assert ctrl_after_full_push({"agent_2": "zero"}).tolist() == by_joint.tolist()
    weak = ctrl_after_full_push({"bfoot": "weak:0.25"})  # torque motors: a quarter the torque
    assert weak.tolist() == [1.0, 1.0, 0.25, 1.0, 1.0, 1.0]
    with pytest.raises(ValueError, match="neither an agent nor an actuated joint.*joints: bthigh"):
        envs.make_team("mamujoco:HalfCheetah-6x1", faults={"tail": "zero"})
    with pytest.raises(ValueError, match="modes 'zero' and 'weak:S' only"):
        envs.make_team("mamujoco:HalfCheetah-6x1", faults={"bfoot": "remove"})


@pytest.mark.parametrize("env_id", ["hopper-2x2", "mamujoco:HalfCheetah-6x1"])
def test_episode_limit_must_be_a_positive_integer(env_id):
    for limit in (0, -5, 2.5):  # 0 used to mean the default, silently
        with pytest.raises(ValueError, match=f"episode_limit must be an integer.* got {limit}"):
            envs.make_team(env_id, episode_limit=limit)
    assert envs.make_team(env_id, episode_limit=7).episode_limit == 7


def test_quadruped_tendon_actuators_own_several_joints():
    team = envs.make_team("quadruped-4x3")
    assert team.joint_names(0) == [
        "yaw_front_left",
        "pitch_front_left",
        "ankle_front_left",
        "knee_front_left",
    ]


@pytest.mark.parametrize("cores", [1, 64], ids=["caller-waits", "caller-steps-a-share"])
def test_vector_env_same_trajectories_whatever_the_worker_count(cores, monkeypatch):
    monkeypatch.setattr(processes, "usable_cores", lambda: cores)

    def run(workers):
        with envs.make_vec(
            "hopper-4x1", num_envs=4, workers=workers, seed=3, episode_limit=12
        ) as vec:
            trace = [vec.reset()]
            rng = np.random.default_rng(0)
            returns = []
            for _ in range(30):
                obs, reward, _, _, info = vec.step(rng.uniform(-1, 1, (4, 4, 1)))
                trace += [obs, reward[:, None, None].astype(np.float32)]
                returns.append(info["episode_return"])
            return np.concatenate([t.reshape(-1) for t in trace]), np.array(returns)

    (local, local_returns), (one, _), (two, two_returns) = run(0), run(1), run(2)
    assert np.array_equal(local, one) and np.array_equal(local, two)
    np.testing.assert_array_equal(local_returns, two_returns)
    finished = ~np.isnan(local_returns)
    assert finished.sum() == 4 * 2  # every copy finished two 12-step episodes in 30 steps


def test_vector_env_autoreset_reports_final_obs_and_episode_stats():
    with envs.make_vec("cheetah-2x3", num_envs=3, seed=0, episode_limit=4) as vec:
        obs = vec.reset()
        for _ in range(4):
            obs, _, _, truncated, info = vec.step(np.zeros((3, 2, 3)))
        assert truncated.all() and (info["episode_length"] == 4).all()
        assert not np.array_equal(info["final_obs"], obs)  # obs is already the next episode's
        with pytest.raises(ValueError, match=r"env 1, agent_0: action contains NaN"):
            bad = np.zeros((3, 2, 3))
            bad[1, 0, 2] = np.nan
            vec.step(bad)
        with pytest.raises(ValueError, match="expected"):
            vec.step(np.zeros((3, 2)))


GL_PROBE = """
import mujoco
context = mujoco.GLContext(32, 24)
context.make_current()
context.free()
"""


def gl_context_problem() -> str | None:
    """Why no OpenGL context can be made here with the backend renders use, or None.

    Asked in a fresh process with the SDK's default backend, so that a failing GL library
    cannot take pytest down and this module's own imports do not matter."""
    environment = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    probe = subprocess.run(
        [sys.executable, "-c", GL_PROBE], env=environment, capture_output=True, text=True
    )
    if probe.returncode == 0:
        return None
    lines = probe.stderr.strip().splitlines() or [f"exit code {probe.returncode}"]
    return f"MUJOCO_GL={environment['MUJOCO_GL']}: {lines[-1]}"


@pytest.mark.parametrize("env_id", ["cheetah-6x1", "mamujoco:HalfCheetah-6x1", "my_robots:arm"])
def test_render_returns_rgb_where_gl_exists(env_id):
    with_examples()  # my_robots: a custom MJCF robot renders like a built-in one
    problem = gl_context_problem()
    if problem:  # only a missing GL context skips; any other render failure fails
        pytest.skip(f"no OpenGL context can be made here ({problem})")
    env = envs.make(env_id, render_mode="rgb_array")
    env.reset(seed=0)
    frame = env.render()
    assert frame.shape == (240, 320, 3) and frame.dtype == np.uint8 and frame.std() > 0
    env.close()


def test_the_game_says_it_has_nothing_to_render():
    with pytest.raises(RuntimeError, match="coordination-3 has no picture to render"):
        envs.make("coordination-3", render_mode="rgb_array").render()


def test_swimmer_family_and_spec_errors():
    assert len(spec_for("swimmer-11").groups) == 10
    with pytest.raises(ValueError, match="N >= 3"):
        spec_for("swimmer-2")


def _team_only_for_seed_0(seed):
    if seed:
        raise RuntimeError(f"no team for seed {seed}")
    return envs.make_team("hopper-4x1", seed=seed)


def test_vector_env_reports_a_worker_that_fails_to_start():
    factory = TeamFactory(_team_only_for_seed_0, {})
    with pytest.raises(RuntimeError, match="env worker failed") as error:
        VecTeam(factory, num_envs=2, workers=1)
    assert "no team for seed 1" in str(error.value)


def _team_that_breaks_in_a_worker(seed):
    team = envs.make_team("hopper-4x1", seed=seed)
    if seed:  # only the worker's copy (seed 1) breaks, on its third step
        advance, calls = team.advance, iter(range(3))

        def breaking_advance(actions):
            if next(calls, None) is None:
                raise FloatingPointError("the simulation diverged")
            return advance(actions)

        team.advance = breaking_advance
    return team


@pytest.mark.parametrize("workers", [1, 2])
def test_vector_env_reports_a_worker_that_fails_or_dies_mid_run(workers):
    factory = TeamFactory(_team_that_breaks_in_a_worker, {})
    vec = VecTeam(factory, num_envs=workers + 1, workers=workers)
    vec.reset()
    actions = np.zeros((workers + 1, 4, 1))
    for _ in range(3):
        vec.step(actions)
    with pytest.raises(RuntimeError, match="env worker failed") as error:
        vec.step(actions)
    assert "FloatingPointError: the simulation diverged" in str(error.value)
    with pytest.raises(RuntimeError, match="closed"):
        vec.step(actions)

    with envs.make_vec("hopper-4x1", num_envs=2, workers=1) as vec:
        vec.reset()
        vec._workers[0].process.kill()
        vec._workers[0].process.join()
        with pytest.raises(RuntimeError, match="a worker process died"):
            vec.step(np.zeros((2, 4, 1)))


def _exited(pid: int) -> bool:
    try:
        with open(f"/proc/{pid}/stat") as stat:
            return stat.read().rsplit(")", 1)[1].split()[0] == "Z"
    except FileNotFoundError:
        return True


@pytest.mark.skipif(not os.path.exists("/proc/self/stat"), reason="needs Linux /proc")
def test_workers_exit_when_their_parent_is_killed():
    script = (
        "import os, signal; from mat_sdk import envs\n"
        "vec = envs.make_vec('hopper-4x1', num_envs=2, workers=1)\n"
        "vec.reset()\n"
        "print(vec._workers[0].process.pid, flush=True)\n"
        "os.kill(os.getpid(), signal.SIGKILL)\n"
    )
    parent = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
    worker = int(parent.stdout.readline())
    parent.wait(timeout=60)
    deadline = time.monotonic() + 10
    while not _exited(worker) and time.monotonic() < deadline:
        time.sleep(0.1)
    orphaned = not _exited(worker)
    if orphaned:
        os.kill(worker, signal.SIGKILL)
    assert not orphaned, "an orphaned env worker kept running after its parent was killed"


def test_actions_that_are_not_real_numbers_are_refused_naming_the_agent():
    game = envs.make("coordination-3")
    for bad, shown in (("1", "'1' (str)"), (True, "True (bool)"), (None, "None (NoneType)")):
        game.reset(seed=0)
        with pytest.raises(
            ValueError, match=re.escape(f"agent_1: action must be a real number, got {shown}")
        ):
            game.step({"agent_0": 0, "agent_1": bad, "agent_2": 2})
    robot = envs.make("cheetah-2x3")
    robot.reset(seed=0)
    leg = robot.agents[1]
    with pytest.raises(ValueError, match=f"{leg}: action must be a real number, got 1j"):
        robot.step({robot.agents[0]: np.zeros(3), leg: np.array([1j, 0, 0])})
    with pytest.raises(ValueError, match=f"{leg}: action must be a real number, got 'a'"):
        robot.step({robot.agents[0]: np.zeros(3), leg: ["a", "b", "c"]})
    team = envs.make_team("cheetah-2x3")
    team.reset(seed=0)
    with pytest.raises(ValueError, match=f"{team.agents[0]}: action must be a real number"):
        team.step(np.full((2, 3), 0.5 + 0.5j))
    vec = envs.make_vec("coordination-3", 2)
    vec.reset(seed=0)
    actions = np.zeros((2, 3, 1), dtype=object)
    actions[1, 2, 0] = None
    with pytest.raises(ValueError, match="env 1, agent_2: action must be a real number, got None"):
        vec.step(actions)


def test_unknown_scenarios_and_options_are_named():
    with pytest.raises(ValueError, match="MaMuJoCo has no scenario 'Nope' with partition '1x1'"):
        envs.make_team("mamujoco:Nope-1x1")
    with pytest.raises(ValueError, match=r"unknown env option\(s\) \['bogus'\] for hopper-2x2"):
        envs.make_team("hopper-2x2", bogus=1)
    with pytest.raises(ValueError, match=r"unknown env option\(s\) \['hops'\] for coordination-3"):
        envs.make_vec("coordination-3", 2, hops=2)


def test_a_diverged_simulation_ends_the_episode_with_a_warning():
    from mat_sdk.envs.core.base import PhysicsDiverged

    robot = envs.make_team("cheetah-2x3")
    robot.reset(seed=0)
    for _ in range(3):  # mid-episode
        robot.step(np.zeros((2, 3)))
    robot._data.qvel[:] = 1e30  # MuJoCo resets such a state silently
    with pytest.warns(PhysicsDiverged, match="cheetah-2x3: the physics diverged at step 4"):
        obs, reward, terminated, truncated = robot.step(np.zeros((2, 3)))
    assert truncated and not terminated and reward == 0.0 and np.isfinite(obs).all()

    scenario = envs.make_team("mamujoco:HalfCheetah-6x1")
    scenario.reset(seed=0)
    for _ in range(3):
        scenario.step(np.zeros((6, 1)))
    scenario._env.single_agent_env.unwrapped.data.qvel[:] = np.nan
    with pytest.warns(PhysicsDiverged, match="HalfCheetah-6x1: the physics diverged"):
        obs, reward, terminated, truncated = scenario.step(np.zeros((6, 1)))
    assert truncated and reward == 0.0 and np.isfinite(obs).all()


def test_a_mamujoco_episode_saved_with_a_damaged_value_is_refused_and_nothing_changes():
    team = envs.make_team("mamujoco:HalfCheetah-6x1", seed=0)
    team.reset(seed=0)
    team.advance(np.zeros((6, 1)))
    saved, before = team.get_state(), team.get_state()
    cases = {
        r"physics state must be \d+ finite numbers .* largest \|value\| nan": {
            "physics": saved["physics"] * np.nan
        },
        r"step count must be a whole number in 0..1000, got 1000000": {"steps": 10**6},
        r"start position must be a number, got inf": {"start_x": np.inf},
        r"random stream must be numpy's generator state": {"random": {"state": 5}},
    }
    for message, change in cases.items():
        with pytest.raises(ValueError, match=message):
            team.set_state({**saved, **change})
        np.testing.assert_array_equal(team.get_state()["physics"], before["physics"])
        assert team.get_state()["steps"] == before["steps"]
