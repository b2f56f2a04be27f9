"""A real robot start to finish, on the trimmed Menagerie Go2 (examples/robots/unitree_go2):
its start pose, observations from hardware signals, joint targets, task terms, training, and
a controller that acts from the robot's sensors through the bundle's wiring."""

from __future__ import annotations

import math
import re
import subprocess
import sys
from pathlib import Path

import mujoco
import numpy as np
import pytest
from helpers import TINY

from mat_sdk import envs
from mat_sdk.envs import Trusted, terms
from mat_sdk.training.trainer import Trainer
from tests.recipes import with_examples

with_examples()
import go2  # noqa: E402  (examples/, put on the path just above)
import go2_controller  # noqa: E402

MJX = (go2.MODELS / "go2_mjx.xml").read_text()  # no floor: it is in scene_mjx.xml
REPO = Path(__file__).resolve().parents[1]


def _team(**options):
    return envs.make_team("go2:walk", **options)


def test_episodes_start_from_home_with_noise_inside_every_joints_range():
    team = _team(seed=0)
    model = team.physics.model.ptr
    home = model.key_qpos[model.key("home").id]
    hinges = [j for j in range(model.njnt) if model.jnt_type[j] == 3]
    starts = []
    for episode in range(40):
        team.reset(seed=episode)
        qpos = team.physics.data.qpos.copy()
        starts.append(qpos)
        assert abs(np.linalg.norm(qpos[3:7]) - 1.0) < 1e-12  # a unit quaternion, turned
        for j in hinges:
            low, high = model.jnt_range[j]
            assert low <= qpos[model.jnt_qposadr[j]] <= high
    starts = np.array(starts)
    assert np.allclose(starts[:, :3], home[:3])  # no position noise unless asked
    assert 0 < np.abs(starts[:, 7:] - home[7:]).max() <= 0.1 + 1e-12  # joint noise, scaled
    assert np.abs(starts[:, 3:7] - home[3:7]).max() > 1e-3  # root_noise turns the base


def test_a_start_outside_a_joints_range_and_an_unknown_keyframe_are_refused():
    no_home = re.sub(r"<keyframe>.*</keyframe>", "", MJX, flags=re.S)
    with pytest.raises(ValueError, match=r"floating base but no 'home' keyframe.*start="):
        envs.from_mjcf(no_home, go2.LAYOUT, go2.REWARD, commands=go2.WALK)
    with pytest.raises(ValueError, match=r"puts joint 'FL_calf_joint' at 0, outside its range"):
        bad = '<key name="bad" qpos="0 0 0.27 1 0 0 0 0 0.9 0 0 0.9 -1.8 0 0.9 -1.8 0 0.9 -1.8"/>'
        keyed = MJX.replace("<keyframe>", f"<keyframe>{bad}")
        envs.from_mjcf(keyed, go2.LAYOUT, go2.REWARD, keyframe="bad", commands=go2.WALK)
    with pytest.raises(ValueError, match="no keyframe named 'crouch'; its keyframes: home"):
        envs.from_mjcf(MJX, go2.LAYOUT, go2.REWARD, keyframe="crouch", commands=go2.WALK)


def test_observations_come_from_the_hardwares_signals_only():
    team = _team(seed=0, command=[0.7, 0.0, 0.0])
    names = [feature.name for feature in team.wiring().observation.features]
    assert names == [
        "joints.pos", "joints.vel", "gravity", "gyro", "contacts", "command", "last_action", "id",
    ]  # fmt: skip
    obs = team.reset(seed=0)
    columns = {f.name: slice(f.start, f.stop) for f in team.wiring().observation.features}
    np.testing.assert_allclose(obs[:, columns["command"]], [[0.7, 0.0, 0.0]] * 4, atol=1e-7)
    assert np.allclose(obs[:, columns["gravity"]][:, 2], -1.0, atol=0.01)  # standing level
    start = team._task.start_qpos
    own = team.physics.data.qpos[7:10] - start[7:10]  # FL's joints, relative to home
    np.testing.assert_allclose(obs[0, columns["joints.pos"]], own, atol=1e-6)
    actions = np.random.default_rng(0).uniform(-1, 1, (4, 3))
    obs, *_ = team.step(actions)
    np.testing.assert_allclose(obs[:, columns["last_action"]], actions, atol=1e-6)


def test_privileged_signals_are_a_choice():
    spec = envs.from_mjcf(
        go2.MODELS / "scene_mjx.xml", go2.LAYOUT, go2.REWARD, commands=go2.WALK,
        observation=envs.Observation(imu="imu", privileged=("height",)), substeps=10,
    )  # fmt: skip
    team = spec.build(seed=0)
    obs = team.reset(seed=0)
    feature = next(f for f in team.wiring().observation.features if f.name == "height")
    assert obs[0, feature.start] == pytest.approx(team.physics.data.qpos[2], abs=1e-6)
    with pytest.raises(ValueError, match="privileged signals are"):
        envs.Observation(privileged=("mass",))


def test_actions_are_joint_targets_around_the_start_pose_clipped_to_the_control_range():
    team = _team(seed=0)
    team.reset(seed=0)
    actions = np.array([[1.0, -1.0, 0.5]] * 4)
    team.step(actions)
    model, ctrl = team.physics.model.ptr, team.physics.data.ctrl
    home = model.key_ctrl[model.key("home").id]
    expected = np.clip(home + 0.5 * actions.reshape(-1), *model.actuator_ctrlrange.T)
    np.testing.assert_allclose(ctrl, expected)
    column = team.wiring().agents[0].action[2]
    assert (column.offset, column.scale, column.target) == (-1.8, 0.5, "FL_calf_joint")


def test_a_pd_layer_turns_targets_into_torques_on_the_torque_motor_model():
    """Menagerie's go2.xml has torque motors: at zero action the PD layer holds the home
    pose, where raw torques (the control range's middle, 0 N m) would let it collapse."""
    team = envs.make_team("go2:walk_torque", seed=0)
    team.reset(seed=0)
    for _ in range(50):
        team.step(np.zeros((4, 3)))
    assert team.physics.data.qpos[2] > 0.2
    forces = team.physics.data.actuator_force
    assert np.all(np.abs(forces) <= team.physics.model.ptr.actuator_ctrlrange[:, 1] + 1e-9)
    column = team.wiring().agents[0].action[0]
    assert (column.kp, column.kd, column.target) == (50.0, 0.5, "FL_hip_joint")
    with pytest.raises(ValueError, match="torque motors: JointTargets needs kp and kd"):
        envs.from_mjcf(go2.MODELS / "scene.xml", go2.LAYOUT, go2.REWARD, commands=go2.WALK,
                       actions=envs.JointTargets(0.5))  # fmt: skip


def test_terms_measure_what_they_name():
    team = _team(seed=0, command=[0.0, 0.0, 0.0])
    team.reset(seed=0)
    step = team._task._step
    data = team.physics.data.ptr
    assert terms.Upright().value(step) == pytest.approx(0.0, abs=3e-3)  # root_noise: a tilt
    assert terms.TrackVelocity().value(step) == pytest.approx(1.0, abs=1e-3)  # still = command
    assert not terms.Tilt(60).ends(step) and not terms.IllegalContact(("base",)).ends(step)
    data.qpos[3:7] = [np.cos(np.pi / 4), np.sin(np.pi / 4), 0, 0]  # on its side
    data.qpos[2] = 0.05
    team.physics.forward()
    assert terms.Tilt(60).ends(step) and terms.Upright().value(step) == pytest.approx(-1.0)
    assert terms.IllegalContact(("base",)).ends(step)
    with pytest.raises(
        ValueError,
        match=r"VelocityCommand.vx must be \[low, high\], two finite numbers with low <= high",
    ):
        terms.VelocityCommand(vx=(1.0, 0.0))
    with pytest.raises(ValueError, match="VelocityCommand.vy must be"):
        terms.VelocityCommand(vy="01")  # not the range (0.0, 1.0)


def test_tracking_over_standing_pays_a_standing_robot_nothing_at_any_command():
    """The plain kernel pays standing still exp(-command^2 / sigma); `over_standing` pays
    what tracking gains over that: 0 for standing, 1 - exp(-command^2 / sigma) for exact."""
    team = _team(seed=0, command=[0.4, 0.0, -0.6])
    team.reset(seed=0)
    step = team._task._step
    still_v, still_yaw = np.exp(-0.16 / 0.25), np.exp(-0.36 / 0.25)
    assert terms.TrackVelocity().value(step) == pytest.approx(still_v, abs=1e-3)
    assert terms.TrackVelocity(over_standing=True).value(step) == pytest.approx(0.0, abs=1e-3)
    assert terms.TrackYawRate().value(step) == pytest.approx(still_yaw, abs=1e-3)
    assert terms.TrackYawRate(over_standing=True).value(step) == pytest.approx(0.0, abs=1e-3)
    data = team.physics.data.ptr
    data.qvel[0], data.qvel[5] = 0.4, -0.6  # the base moves as told (it starts level)
    team.physics.forward()
    assert terms.TrackVelocity(over_standing=True).value(step) == pytest.approx(
        1 - still_v, abs=2e-2
    )
    assert terms.TrackYawRate(over_standing=True).value(step) == pytest.approx(
        1 - still_yaw, abs=2e-2
    )


def _standing(command):
    """A Go2 settled on its four feet at `command`: the team, its terms' step, its data."""
    team = _team(seed=0, command=command)
    team.reset(seed=0)
    for _ in range(50):
        team.step(np.zeros((4, 3)))
    return team, team._task._step, team.physics.data.ptr


def test_feet_slip_costs_a_sliding_foot_on_the_floor_and_nothing_in_the_air():
    team, step, data = _standing([0.0, 0.0, 0.0])
    slip = terms.FeetSlip(feet=("FL", "FR", "RL", "RR"))
    assert slip.value(step) == pytest.approx(0.0, abs=1e-3)  # standing: feet planted
    data.qvel[:] = 0.0
    data.qvel[0] = 0.5  # the whole robot slides forward at 0.5 m/s, every foot on the floor
    team.physics.forward()
    assert slip.value(step) == pytest.approx(-4 * 0.25 / step.scale.speed**2, rel=1e-6)
    data.qpos[2] += 0.2  # lifted: no foot on the floor, no slip
    team.physics.forward()
    assert slip.value(step) == 0.0
    with pytest.raises(ValueError, match="'paw' is neither a geom nor a body of the model"):
        terms.FeetSlip(feet=("paw",)).value(step)


def test_feet_rhythm_pays_phases_up_to_the_robots_step_time_and_a_planted_foot_nothing():
    team, step, data = _standing([0.7, 0.0, 0.0])
    rhythm = terms.FeetRhythm(feet=("FL", "FR", "RL", "RR"))
    phase = 1.3 * math.sqrt(step.scale.height / step.scale.gravity)  # 0.2 s on the Go2
    within = math.floor(phase / step.control_timestep)  # steps whose phase time pays
    earned = [rhythm.value(step) for _ in range(within + 2)]
    assert earned[0] == pytest.approx(step.control_timestep / phase)  # the phase's first step
    assert earned[within - 1] == pytest.approx(within * step.control_timestep / phase)
    assert earned[-2:] == [0.0, 0.0]  # planted for longer than a step: nothing
    data.qpos[2] += 0.2  # lifted: every foot starts a new phase, in the air
    team.physics.forward()
    assert rhythm.value(step) == pytest.approx(step.control_timestep / phase)
    step.command[:] = 0.0  # told to stand: time in the air costs
    assert rhythm.value(step) == pytest.approx(-2 * step.control_timestep / phase)


def test_go2_trains_for_a_few_updates_and_resumes_exactly(tmp_path):
    options = {**TINY, "num_envs": 2, "rollout_length": 20}
    with Trainer("go2:walk", out_dir=tmp_path / "a", **options) as trainer:
        trainer.learn(40, progress_bar=False)
        trainer.save(tmp_path / "half.pt")
        trainer.learn(80, progress_bar=False)
        straight = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    with Trainer.load(Trusted(tmp_path / "half.pt"), out_dir=tmp_path / "b") as again:
        again.learn(80, progress_bar=False)
        for name, value in again.policy.state_dict().items():
            assert np.array_equal(value.numpy(), straight[name].numpy()), name


def test_the_controller_builds_the_envs_observation_from_the_robots_sensors(go2_bundle):
    """The same state through two doors: the env's own observation, and the wiring fed with
    what the hardware reads (encoders, IMU, contacts), the command and the last action."""
    from mat_runtime import Policy

    policy = Policy.load(go2_bundle)
    wiring = policy.wiring
    team = _team(seed=0, command=[0.5, 0.0, 0.2])
    robot = go2_controller.SimulatedGo2(
        go2.MODELS / "scene_mjx.xml", wiring.signals["joint_pos"], wiring.signals["contacts"],
        wiring.control_timestep,
    )  # fmt: skip
    robot.model, robot.data = team.physics.model.ptr, team.physics.data.ptr  # the env's state
    obs, last = team.reset(seed=0), np.zeros(12)
    rng = np.random.default_rng(0)
    for _ in range(25):
        built = wiring.observe(**robot.read()[0], command=[0.5, 0.0, 0.2], last_action=last)
        np.testing.assert_allclose(built, obs, rtol=1e-5, atol=1e-5)
        actions = rng.uniform(-1, 1, (4, 3))
        obs, *_ = team.step(actions)
        last = actions.reshape(-1)
        index, targets = wiring.commands(actions)
        np.testing.assert_allclose(team.physics.data.ctrl[index], targets, atol=1e-12)
    described = policy.describe()
    for signal in ("joint_pos", "joint_vel", "gravity", "gyro", "contacts", "command"):
        assert f"signal {signal}:" in described
    with pytest.raises(ValueError, match="signal gravity is missing"):
        wiring.observe(joint_pos=np.zeros(12), joint_vel=np.zeros(12))


def test_the_go2_controller_runs_without_torch(go2_bundle):
    run = subprocess.run(
        [sys.executable, str(REPO / "examples" / "go2_controller.py"), str(go2_bundle),
         "--seconds", "1"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "falls" in run.stdout and re.search(r"late ticks: \d+", run.stdout)


def test_the_go2_controller_plays_a_scripted_joystick_and_reports_tracking(go2_bundle):
    """The script at a quarter of its length (real time): a row per segment, the operator's
    command, what the kit gave the policy (clamped to the trained ranges) and the measured
    velocity where the policy had a settled moment, and the summary."""
    run = subprocess.run(
        [sys.executable, str(REPO / "examples" / "go2_controller.py"), str(go2_bundle),
         "--joystick", "--seconds", "6.5"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    rows = re.findall(r"^\s+\d+\.\d+\s+\(([^)]*)\)(.*)$", run.stdout, re.M)
    operator = [tuple(float(v) for v in command.split(",")) for command, _ in rows]
    assert operator == [(0, 0, 0), (0.6, 0, 0), (0, 0, 0), (0, 0, 0.8), (0, 0.3, 0), (-0.3, 0, 0)]
    turn = re.findall(r"\(([^)]*)\)", rows[3][1])
    if turn:  # the go2:walk policy was trained on no yaw rate: the kit gave it 0
        assert float(turn[0].split(",")[2]) == 0.0
    assert "mean |error| over" in run.stdout or "no policy time" in run.stdout


def test_a_model_without_a_camera_is_filmed_by_a_following_camera():
    team = _team(seed=0)
    team.reset(seed=0)
    try:
        frame = team.render(height=60, width=80)
    except RuntimeError as error:
        pytest.skip(f"no GL here: {error}")
    assert frame.shape == (60, 80, 3) and frame.std() > 5


def test_actuators_left_to_no_agent_are_named():
    with pytest.warns(envs.UnusedActuators, match=r"leaves actuators \['RR_hip'"):
        layout = {**go2.LAYOUT, "RR": ["RR_thigh", "RR_calf"]}
        envs.from_mjcf(
            go2.MODELS / "scene_mjx.xml", layout, go2.REWARD, commands=go2.WALK, substeps=10
        )


def test_mat_train_says_when_it_trains_more_steps_than_asked(tmp_path):
    run = subprocess.run(
        [str(Path(sys.executable).with_name("mat")), "train", "coordination-2", "--steps", "10",
         "--num-envs", "4", "--set", "rollout_length=4", "--set", "num_minibatches=1",
         "--out", str(tmp_path / "r"), "--quiet"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert "--steps 10: training runs whole updates of 16 env steps" in run.stdout
    assert "this run ends at 16 steps" in run.stdout


@pytest.mark.slow
def test_every_command_of_the_real_robot_tutorial_runs(tmp_path):
    """docs/REAL_ROBOTS.md's tutorial (section 6) as a user runs it, shortened to one update,
    one episode and one second: train a seed set, evaluate at 0.7 m/s, export, run the
    controller from the robot's sensors. (Section 8's randomization is tested on its own.)"""
    import os
    import shlex

    page = (REPO / "docs" / "REAL_ROBOTS.md").read_text()
    text = page.split("## 6. ")[1].split("\n## 7. ")[0]
    lines = [line for block in re.findall(r"```bash\n(.*?)```", text, flags=re.S)
             for line in block.splitlines() if line and not line.startswith("export ")]  # fmt: skip
    programs = [line.split()[:2] for line in lines]
    assert programs == [["mat", "train"], ["mat", "eval"], ["mat", "export"],
                        ["python", "examples/go2_controller.py"]]  # fmt: skip
    short = {"--seeds": "1", "--steps": "1", "--episodes": "1", "--seconds": "1"}
    (tmp_path / "examples").symlink_to(REPO / "examples")
    environment = {**os.environ, "PYTHONPATH": str(tmp_path / "examples")}
    outputs = []
    for line in lines:
        words = shlex.split(line, comments=True)
        words = [short.get(words[i - 1], word) if i else word for i, word in enumerate(words)]
        program = (
            [str(Path(sys.executable).with_name("mat"))] if words[0] == "mat" else [sys.executable]
        )
        run = subprocess.run([*program, *words[1:]], cwd=tmp_path, env=environment,
                             capture_output=True, text=True, timeout=600)  # fmt: skip
        assert run.returncode == 0, f"{line}\n{run.stdout}\n{run.stderr}"
        outputs.append(run.stdout)
    assert "forward speed" in outputs[1] and "falls" in outputs[3]


@pytest.mark.parametrize("env_id", ["go2:walk", "go2:walk_torque"])
def test_a_weak_fault_scales_that_motors_force_and_no_other(env_id):
    """A position actuator (kp, kv, force limit) and a torque motor behind the PD layer alike:
    at the same state and controls the weak knee gives 0.4 of its force, the rest the same."""
    forces = []
    for faults in ({}, {"FR_calf_joint": "weak:0.4"}):
        team = envs.make_team(env_id, faults=faults, seed=0)
        team.reset(seed=0)
        data = team.physics.data.ptr
        data.ctrl[:] = np.clip(data.ctrl + 0.3, *team.physics.model.ptr.actuator_ctrlrange.T)
        mujoco.mj_forward(team.physics.model.ptr, data)
        forces.append(data.actuator_force.copy())
    knee = team.physics.model.ptr.actuator("FR_calf").id
    assert abs(forces[0][knee]) > 1.0
    np.testing.assert_allclose(forces[1][knee], 0.4 * forces[0][knee])
    others = np.arange(len(forces[0])) != knee
    np.testing.assert_array_equal(forces[1][others], forces[0][others])
    assert team.agents == envs.make_team(env_id).agents  # the agent stays, its joint works


@pytest.mark.parametrize("mode", ["weak:0", "weak:1", "weak:1.5", "weak:nan", "weak:", "weak:x"])
def test_a_weak_fault_outside_0_to_1_is_refused_naming_it(mode):
    with pytest.raises(ValueError, match=f"fault FR_calf_joint='{mode}'.*strictly between 0 and 1"):
        envs.make_team("go2:walk", faults={"FR_calf_joint": mode})


@pytest.mark.parametrize(
    ("edit", "problem"),
    [
        (
            lambda w: w["observation"]["signals"]["joint_pos"].__setitem__(0, "no_joint"),
            "names what scene_mjx.xml does not have",
        ),
        (
            lambda w: w["observation"]["signals"].pop("contacts"),
            "does not observe the Go2's joint encoders and foot contacts",
        ),
        (
            lambda w: w["agents"][0]["action"][0].__setitem__("ctrl", 10**4),
            "drives actuator 10000, and scene_mjx.xml has 12",
        ),
        (lambda w: w.__setitem__("control_timestep", 1e300), "control_timestep must be in"),
        (lambda w: w.__setitem__("control_timestep", 1e-300), "control_timestep must be in"),
    ],
    ids=["joint", "contacts", "ctrl", "slow", "fast"],
)
def test_the_go2_controller_refuses_an_edited_bundle_in_one_line(
    go2_bundle, tmp_path, edit, problem
):
    import json
    import shutil

    edited = tmp_path / "onnx"
    shutil.copytree(go2_bundle, edited)
    manifest = json.loads((edited / "manifest.json").read_text())
    edit(manifest["wiring"])
    (edited / "manifest.json").write_text(json.dumps(manifest))
    run = subprocess.run(
        [sys.executable, str(REPO / "examples" / "go2_controller.py"), str(edited),
         "--seconds", "0.2"],
        capture_output=True, text=True, timeout=120,
    )  # fmt: skip
    assert run.returncode != 0 and problem in run.stderr, run.stderr
    assert "Traceback" not in run.stderr
