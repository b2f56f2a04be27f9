"""One task definition for any legged robot (`mat_sdk.envs.tasks.legged`): robot-relative terms,
named per-term logs, start poses from joint angles, the task's training recipe and lean
physics copies, on the trimmed Menagerie Go2, A1 and Spot in examples/robots/."""

from __future__ import annotations

import copy
import csv
import re

import mujoco
import numpy as np
import pytest
from helpers import TINY

from mat_sdk import envs
from mat_sdk.envs import Trusted, terms
from mat_sdk.envs.tasks.legged import JOYSTICK, WALK
from mat_sdk.training.runs import RunRequest, with_task_recipe
from mat_sdk.training.trainer import Trainer
from tests.recipes import with_examples

with_examples()
import quadrupeds  # noqa: E402  (examples/, put on the path just above)


@pytest.mark.parametrize("robot", ["go2", "a1", "spot"])
def test_each_terms_share_is_logged_and_they_sum_to_the_reward(robot):
    team = envs.make_team(f"quadrupeds:{robot}", seed=0)
    assert team.reward_terms == (*(t.name for t in WALK.reward), "floor")
    team.reset(seed=0)
    random = np.random.default_rng(0)
    floored = 0
    for _ in range(60):
        _, reward, terminated, _ = team.advance(random.uniform(-1, 1, (4, 3)))
        values = team.term_values()
        assert values.sum() == pytest.approx(reward, abs=1e-9)
        assert reward >= 0.0 and values[-1] >= 0.0  # only positive rewards: the floor lifts
        floored += values[-1] > 0
        if terminated:
            team.reset()
    assert floored > 0  # random actions cost more than they earn somewhere: the floor acts


def test_training_writes_each_terms_mean_per_step(tmp_path):
    with Trainer("quadrupeds:a1", out_dir=tmp_path, **TINY) as trainer:
        trainer.learn(2 * TINY["num_envs"] * TINY["rollout_length"], progress_bar=False)
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    names = [f"reward/{t.name}" for t in WALK.reward] + ["reward/floor"]
    for row in rows:
        total = sum(float(row[name]) for name in names)
        assert total == pytest.approx(float(row["reward_per_step"]), rel=1e-4, abs=1e-5)


def test_a_start_pose_is_lowered_until_the_feet_touch_the_floor():
    """The A1 from joint angles (its keyframe ignored) starts where its keyframe has it: the
    base within 5 mm of the keyframe's 0.27 m, every foot on the floor, nothing in it."""
    team = envs.make_team("quadrupeds:a1", seed=0, randomize=False)
    model = team.physics.model.ptr
    start = team._task.start_qpos
    assert start[2] == pytest.approx(0.27, abs=5e-3)
    data = mujoco.MjData(model)
    data.qpos[:] = start
    mujoco.mj_forward(model, data)
    assert data.ncon == 0  # nothing in the floor
    data.qpos[2] -= 5e-4  # half a millimetre lower, every foot touches it
    mujoco.mj_forward(model, data)
    contacts = data.contact[: data.ncon]
    bodies = {model.body(int(model.geom_bodyid[g])).name for g in contacts.geom.reshape(-1)}
    assert {f"{leg}_calf" for leg in quadrupeds.LEGS} <= bodies
    assert contacts.dist.min() > -1e-3


def test_a_floating_base_without_a_keyframe_or_start_is_refused(tmp_path):
    folder = quadrupeds.ROBOTS / "unitree_a1"
    xml = (folder / "a1.xml").read_text()
    (tmp_path / "a1.xml").write_text(re.sub(r"<keyframe>.*</keyframe>", "", xml, flags=re.S))
    (tmp_path / "scene.xml").write_text((folder / "scene.xml").read_text())
    no_key = tmp_path / "scene.xml"
    layout = {leg: [f"{leg}_hip", f"{leg}_thigh", f"{leg}_calf"] for leg in quadrupeds.LEGS}
    with pytest.raises(ValueError, match=r"floating base but no 'home' keyframe.*start="):
        envs.from_mjcf(no_key, layout, [terms.Alive(1.0)])
    spec = envs.from_mjcf(no_key, layout, [terms.Alive(1.0)], start=quadrupeds.A1.start)
    assert spec.build(seed=0)._task.start_qpos[2] > 0.2  # standing, not straight-legged


def test_robot_relative_penalties_do_not_change_when_masses_and_forces_scale_together():
    """A robot twice as heavy with motors twice as strong moves the same way: its relative
    effort, power and bouncing cost the same, the absolute forms do not."""
    source = envs.make_team("quadrupeds:spot", seed=0, randomize=False).physics.model.ptr
    values = {}
    for factor in (1.0, 2.0):
        model = copy.copy(source)
        model.body_mass[:] *= factor
        model.body_inertia[:] *= factor
        model.actuator_gainprm[:, 0] *= factor
        model.actuator_biasprm[:, :3] *= factor
        data = mujoco.MjData(model)
        mujoco.mj_setConst(model, data)  # the solver's inertia-derived constants
        mujoco.mj_resetDataKeyframe(model, data, 0)
        step = terms.Step(
            data, model, terms_trunk(model), np.zeros(3), np.zeros(12), np.zeros(12), 0.02,
            terms.RobotScale.of(model, data.qpos[2]),
        )  # fmt: skip
        random = np.random.default_rng(0)
        totals = np.zeros(5)
        for _ in range(50):
            data.ctrl[:] = model.key_ctrl[0] + random.uniform(-0.3, 0.3, model.nu)
            mujoco.mj_step(model, data, 10)
            totals += [
                terms.Torque().value(step), terms.Energy().value(step),
                terms.VerticalVelocity().value(step), terms.Torque(relative=False).value(step),
                terms.Energy(relative=False).value(step),
            ]  # fmt: skip
        values[factor] = totals
    relative, absolute = slice(0, 3), slice(3, 5)
    assert np.allclose(values[1.0][relative], values[2.0][relative], rtol=1e-3)
    assert np.all(np.abs(values[2.0][absolute]) > 1.9 * np.abs(values[1.0][absolute]))


def terms_trunk(model):
    from mat_sdk.envs.mujoco.trunk import Trunk

    return Trunk(model)


def test_joint_targets_reach_as_far_as_the_robots_weight_moment_over_each_stiffness():
    scales = {}
    for robot in ("go2", "a1", "spot"):
        team = envs.make_team(f"quadrupeds:{robot}", seed=0)
        scale = team._task._step.scale
        kp = -team.physics.model.ptr.actuator_biasprm[:, 1]
        assert np.allclose(team.actions.targets.scale, WALK.action_torque * scale.torque / kp)
        scales[robot] = float(team.actions.targets.scale[0])
    assert scales["go2"] == pytest.approx(0.5, abs=0.01)  # the Go2's measured 0.5 rad
    assert scales["a1"] < scales["spot"] < scales["go2"]  # A1's kp 100, Spot's 500


def test_the_task_recipe_is_what_mat_train_and_trainer_use_unless_overridden():
    recipe = WALK.recipe.settings()
    with Trainer("quadrupeds:a1", num_envs=2, rollout_length=5) as trainer:
        config = trainer.config
        assert (config.ppo.num_envs, config.ppo.rollout_length) == (2, 5)  # the caller's
        assert config.ppo.lr == recipe["lr"] and config.ppo.entropy_coef == recipe["entropy_coef"]
    request = RunRequest(["quadrupeds:a1"], options={"num_envs": 8, "lr": 1e-3}, given=["lr"])
    chosen = with_task_recipe(request)
    assert chosen.options["num_envs"] == recipe["num_envs"]  # a CLI default gives way
    assert chosen.options["lr"] == 1e-3  # what the user chose does not
    assert chosen.tune is True and chosen.evaluation_interval == 0  # the task's way to run
    given = with_task_recipe(RunRequest(["quadrupeds:a1"], eval_every=5000, tune=False))
    assert given.tune is False and given.evaluation_interval == 5000


TEXTURED = """
<mujoco>
  <asset>
    <texture name="big" type="2d" builtin="checker" width="2048" height="2048"/>
    <material name="skin" texture="big"/>
  </asset>
  <worldbody>
    <geom type="plane" size="5 5 .1"/>
    <body name="base" pos="0 0 .5">
      <freejoint/>
      <geom type="box" size=".1 .1 .1"/>
      <geom type="sphere" size=".12" material="skin" contype="0" conaffinity="0"/>
      <body name="leg">
        <joint name="hip" axis="0 1 0" range="-1 1"/>
        <geom type="capsule" fromto="0 0 0 0 0 -.3" size=".02"/>
      </body>
    </body>
  </worldbody>
  <actuator><position name="hip" joint="hip" kp="20"/></actuator>
  <keyframe><key name="home" qpos="0 0 .45 1 0 0 0 0" ctrl="0"/></keyframe>
</mujoco>
"""


def test_physics_copies_carry_no_visual_assets():
    """A 2048 x 2048 texture (12 MB) and a visual-only geom stay out of every env copy."""
    full = mujoco.MjModel.from_xml_string(TEXTURED)
    team = envs.from_mjcf(TEXTURED, {"leg": ["hip"]}, [terms.Alive(1.0)]).build(seed=0)
    lean = team.physics.model.ptr
    assert full.ntex == 1 and full.ntexdata > 10_000_000
    assert lean.ntex == 0 and lean.ngeom == full.ngeom - 1


def test_a_penalty_in_another_robots_units_is_warned_about_before_training():
    """The Go2's absolute torque weight on a robot where it costs far more than any positive
    term earns: the trainer warns, naming the term; the robot-relative task does not."""
    from mat_sdk.envs.tasks.reward_check import RewardWarning

    heavy = [terms.Alive(0.25), terms.Torque(1e-2, relative=False)]
    spec = envs.from_mjcf(
        quadrupeds.SPOT.model, quadrupeds.SPOT.layout, heavy, actions=envs.JointTargets(0.5)
    )
    with pytest.warns(RewardWarning, match="reward term 'torque' costs"):
        Trainer(spec, **TINY).close()
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("error", RewardWarning)
        Trainer("quadrupeds:spot", **TINY).close()


def test_mat_eval_breaks_the_reward_down_by_term(tmp_path):
    from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate_episodes

    with Trainer("quadrupeds:a1", **TINY) as trainer:
        path = trainer.save(tmp_path / "a1.pt")
    loaded = CheckpointPolicy.from_checkpoint(Trusted(path))
    episodes = evaluate_episodes(loaded, 2, episode_limit=30)
    assert set(episodes.terms) == {*(t.name for t in WALK.reward), "floor"}
    steps = sum(episodes.lengths)
    assert sum(episodes.terms.values()) * steps == pytest.approx(sum(episodes.returns), rel=1e-6)
    table = episodes.breakdown()
    assert table.splitlines()[0].startswith("reward term") and "track_velocity" in table


GRIPPER = """
<mujoco>
  <worldbody>
    <body name="palm">
      <joint name="wrist" axis="0 0 1" range="-1 1"/>
      <geom type="box" size=".04 .02 .02"/>
      <body name="left"><joint name="left" type="slide" axis="1 0 0" range="0 0.037"/>
        <geom type="box" size=".005 .01 .03" pos=".02 0 -.04"/></body>
      <body name="right"><joint name="right" type="slide" axis="-1 0 0" range="0 0.037"/>
        <geom type="box" size=".005 .01 .03" pos="-.02 0 -.04"/></body>
    </body>
  </worldbody>
  <equality><joint joint1="right" joint2="left" polycoef="0 1 0 0 0"/></equality>
  <actuator>
    <position name="wrist" joint="wrist" kp="10"/>
    <position name="grip" joint="left" kp="100" ctrlrange="0 0.037"/>
  </actuator>
</mujoco>
"""


def test_reset_noise_keeps_coupled_fingers_coupled_and_in_range():
    """A gripper's second finger follows the first through its joint equality at every
    reset, from the task's noise and the randomization's start noise alike."""
    spec = envs.from_mjcf(
        GRIPPER, {"wrist": ["wrist"], "hand": ["grip"]}, lambda physics: 0.0,
        reset_noise=0.5, randomize={"defaults": False, "start": 0.5},
    )  # fmt: skip
    team = spec.build(seed=0)
    model = team.physics.model.ptr
    left, right = (model.jnt_qposadr[model.joint(n).id] for n in ("left", "right"))
    positions = []
    for episode in range(30):
        team.reset(seed=episode)
        qpos = team.physics.data.qpos
        assert qpos[right] == pytest.approx(qpos[left], abs=1e-12)
        assert 0.0 <= qpos[left] <= 0.037
        positions.append(qpos[left])
    assert np.ptp(positions) > 0.01  # the noise moves the fingers, together


def test_a_video_is_rendered_at_its_frame_rate_from_a_copy_with_the_visual_assets(tmp_path):
    """At 50 Hz control, a 30 fps video renders every other step (20 steps, 10 frames), and
    its recorder keeps the texture that the env copies leave out."""
    import imageio.v2 as imageio
    from test_envs import gl_context_problem

    from mat_sdk.evaluation.episodes import evaluate_episodes

    problem = gl_context_problem()
    if problem:  # only a missing GL context skips; any other render failure fails
        pytest.skip(f"no OpenGL context can be made here ({problem})")
    spec = envs.from_mjcf(
        TEXTURED, {"leg": ["hip"]}, [terms.Alive(1.0)], substeps=10, episode_limit=20
    )
    assert envs.make_team(spec, visual=True).physics.model.ptr.ntex == 1
    with Trainer(spec, **TINY) as trainer:
        loaded = trainer._as_loaded()
        evaluate_episodes(loaded, 1, video=tmp_path / "run.gif")
    assert len(imageio.mimread(tmp_path / "run.gif")) == 10


def test_tracking_reports_the_bases_velocity_in_its_heading_frame_after_the_first_second():
    """A Go2 turned to face +y and carried at 0.4 m/s along +y (forward for it) and 0.2 m/s
    along -x (its left) while yawing at 0.5 rad/s: (0.4, 0.2, 0.5)."""
    team = envs.make_team("quadrupeds:go2", seed=0)
    team.reset(seed=0)
    physics = team.physics
    base = team._base
    data = physics.data.ptr
    quarter = np.array([np.cos(np.pi / 4), 0.0, 0.0, np.sin(np.pi / 4)])  # 90 degrees of yaw
    assert np.isnan(team.tracking()).all()  # nothing measured in the first second
    for _ in range(60):
        data.qpos[base.qpos + 3 : base.qpos + 7] = quarter
        data.qpos[base.qpos + 2] = 0.3
        data.qvel[base.qvel : base.qvel + 6] = [-0.2, 0.4, 0.0, 0.0, 0.0, 0.5]
        mujoco.mj_forward(physics.model.ptr, data)
        team._track()
    np.testing.assert_allclose(team.tracking(), [0.4, 0.2, 0.5], atol=1e-9)


def test_mat_eval_grid_reports_tracking_per_command_and_plots_it(tmp_path):
    from click.testing import CliRunner

    from mat_sdk.cli import main
    from mat_sdk.evaluation.tracking import JOYSTICK_GRID

    with Trainer("quadrupeds:go2", **TINY) as trainer:
        path = trainer.save(tmp_path / "go2.pt")
    plot = tmp_path / "tracking.png"
    args = ["eval", str(path), "--grid", "--episodes", "1", "--plot", str(plot),
            "--env-option", "episode_limit=60", "--trust-env-code"]  # fmt: skip
    result = CliRunner().invoke(main, args)
    assert result.exit_code == 0, result.output
    rows = [line for line in result.output.splitlines() if re.match(r"\| -?\d", line)]
    assert len(rows) == len(JOYSTICK_GRID) and rows[0].startswith("| 0, 0, 0 |")
    assert "mean absolute error over the" in result.output and plot.stat().st_size > 0
    both = CliRunner().invoke(main, [*args, "--sweep", "payload=0,1"])
    assert both.exit_code == 2 and "--sweep and --grid are two reports" in both.output
    commanded = CliRunner().invoke(main, [*args, "--env-option", "command=[1,0,0]"])
    assert commanded.exit_code == 2 and "--grid sets the command itself" in commanded.output
    own = CliRunner().invoke(
        main, [*args, "--grid-command", "0,0.3,0", "--grid-command", "-0.2,0,1"]
    )
    rows = [line for line in own.output.splitlines() if re.match(r"\| -?\d", line)]
    assert own.exit_code == 0 and [row.split(" |")[0] for row in rows] == [
        "| 0, 0.3, 0",
        "| -0.2, 0, 1",
    ]
    for bad in ("0.3,0", "0,nan,0", "fast,0,0", "0,0,11"):
        refused = CliRunner().invoke(main, [*args, "--grid-command", bad])
        assert refused.exit_code == 2 and "a grid command is VX,VY,YAW" in refused.output
        assert repr(bad) in refused.output
    alone = CliRunner().invoke(main, ["eval", str(path), "--grid-command", "0,0,0"])
    assert alone.exit_code == 2 and "--grid-command gives the rows of a --grid" in alone.output


def test_a_joystick_command_changes_within_an_episode_stands_on_purpose_and_resumes_exactly():
    """`legged.JOYSTICK`: a new command every 5 s (250 steps), one observed by the step after
    the reward that followed the old one; a tenth of them zero; a team restored mid-period
    draws the same next command."""
    team = envs.make_team("quadrupeds:go2_joystick", seed=3)
    team.reset(seed=3)
    task, zero = team._task, np.zeros((4, 3))
    commands = [task.command.copy()]
    for step in range(1, 751):
        team.advance(zero)
        if step == 100:
            saved = team.get_state()
        if not np.array_equal(task.command, commands[-1]):
            assert step % 250 == 0, step  # on the period, not between
            commands.append(task.command.copy())
    assert len(commands) == 4  # the first and three resampled
    restored = envs.make_team("quadrupeds:go2_joystick", seed=99)
    restored.reset(seed=99)
    restored.set_state(saved)
    for _ in range(150):
        restored.advance(zero)
    assert np.array_equal(restored._task.command, commands[1])
    draws = JOYSTICK.commands
    random = np.random.RandomState(0)
    samples = np.array([draws.sample(random) for _ in range(4000)])
    standing = (samples == 0).all(axis=1).mean()
    assert 0.08 < standing < 0.12  # the share asked for
    assert samples[:, 0].min() < -0.4 and samples[:, 1].max() > 0.4 and samples[:, 2].min() < -0.9


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"standing": 1.5}, r"VelocityCommand.standing is a share in \[0, 1\], got 1.5"),
        (
            {"resample_seconds": 0},
            "VelocityCommand.resample_seconds must be a number of seconds > 0",
        ),
    ],
)
def test_a_joystick_setting_out_of_range_is_refused_naming_it(options, message):
    with pytest.raises(ValueError, match=message):
        terms.VelocityCommand(vx=(0.0, 1.0), **options)


def test_stand_still_pays_joints_near_the_start_pose_at_a_zero_command_only():
    team = envs.make_team("quadrupeds:go2_joystick", seed=0, randomize=False, command=[0, 0, 0])
    team.reset(seed=0)
    index = team.reward_terms.index("stand_still")
    for _ in range(10):
        team.advance(np.zeros((4, 3)))  # joint targets at the start pose
    resting = team.term_values()[index]
    for _ in range(10):
        team.advance(np.full((4, 3), 0.8))  # every joint driven away from it
    driven = team.term_values()[index]
    assert 0.3 < resting <= 0.5  # weight 0.5: near the pose, most of it
    assert 0 < driven < 0.5 * resting  # a kernel: less far away, never a cost
    moving = envs.make_team("quadrupeds:go2_joystick", seed=0, randomize=False, command=[0.5, 0, 0])
    moving.reset(seed=0)
    moving.advance(np.zeros((4, 3)))
    assert moving.term_values()[index] == 0.0  # told to move: nothing


def test_a_command_curriculum_widens_from_its_first_ranges_to_the_commands_own():
    curriculum = terms.CommandCurriculum(vx=(0.3, 1.0), levels=10)
    command = terms.VelocityCommand(
        vx=(-0.5, 1.0), vy=(-0.5, 0.5), yaw_rate=(-1.0, 1.0), curriculum=curriculum
    )
    np.testing.assert_allclose(command.ranges(0), [[0.3, 1.0], [0, 0], [0, 0]])
    np.testing.assert_allclose(command.ranges(5), [[-0.1, 1.0], [-0.25, 0.25], [-0.5, 0.5]])
    np.testing.assert_allclose(command.ranges(10), command.ranges())  # the command's own
    random = np.random.RandomState(0)
    first = np.array([command.sample(random, level=0) for _ in range(200)])
    assert first[:, 0].min() >= 0.3 and (first[:, 1:] == 0).all()


def _free_box() -> tuple[mujoco.MjModel, mujoco.MjData]:
    model = mujoco.MjModel.from_xml_string(
        '<mujoco><worldbody><body name="base"><freejoint/><geom size="0.1"/></body>'
        "</worldbody></mujoco>"
    )
    return model, mujoco.MjData(model)


def test_curriculum_levels_rise_when_commands_are_followed_and_drop_when_missed_or_fallen():
    from mat_sdk.envs.mujoco.curriculum import CurriculumProgress
    from mat_sdk.envs.mujoco.trunk import Trunk

    model, data = _free_box()
    mujoco.mj_kinematics(model, data)  # level, facing +x: base frame = world frame
    curriculum = terms.CommandCurriculum(levels=2, tolerance=(0.1, 0.2))
    progress = CurriculumProgress(curriculum, Trunk(model), settle_steps=5)
    command = np.array([0.5, 0.0, 0.3])

    def follow(vx, yaw_rate, settle=(0.0, 0.0), steps=20):
        for velocity in [settle] * 5 + [(vx, yaw_rate)] * steps:
            data.qvel[0], data.qvel[5] = velocity
            progress.follow(data, command)

    follow(0.45, 0.3, settle=(-3.0, 3.0))  # the first second's errors are not counted
    progress.judge(fell=False)
    assert progress.level == 1 and progress.share == 0.5
    follow(0.35, 0.3)  # 0.15 m/s off: neither up nor down
    progress.judge(fell=False)
    follow(0.5, 0.0)  # 0.3 rad/s off: neither
    progress.judge(fell=False)
    assert progress.level == 1
    follow(0.0, 0.3)  # standing where it should walk: 0.5 m/s off, over twice the tolerance
    progress.judge(fell=False)
    assert progress.level == 0
    follow(0.5, 0.3)
    progress.judge(fell=False)
    assert progress.level == 1
    follow(0.5, 0.3, steps=2)  # cut short: under a second measured, not judged
    progress.judge(fell=False)
    assert progress.level == 1
    follow(0.5, 0.3)
    progress.judge(fell=True)  # however well it went until then
    assert progress.level == 0
    for _ in range(3):
        follow(0.5, 0.3)
        progress.judge(fell=False)
    assert progress.level == 2  # the top: the command's own ranges
    follow(0.5, 0.3, steps=7)
    saved = progress.get_state()
    restored = CurriculumProgress(curriculum, Trunk(model), settle_steps=5)
    restored.set_state(saved)
    assert restored.get_state()["steps"] == 12 and restored.level == 2
    with pytest.raises(ValueError, match=r"curriculum level must be a whole number in 0..2, got 3"):
        restored.set_state({**saved, "level": 3})
    for level in (np.nan, 1.5, "two"):
        with pytest.raises(ValueError, match=r"level must be a whole number in 0..2, got"):
            restored.set_state({**saved, "level": level})
    for steps in (-1, np.inf, 2.5):
        with pytest.raises(ValueError, match=r"curriculum step count must be a whole number"):
            restored.set_state({**saved, "steps": steps})
    for errors in ([np.nan, 0.0, 1.0], [0.5, -1.0, 1.0], [0.5, 1.0]):
        with pytest.raises(ValueError, match=r"curriculum errors must be 3 finite numbers >= 0"):
            restored.set_state({**saved, "errors": errors})
    assert restored.level == 2 and restored.get_state()["steps"] == 12  # nothing taken from it


@pytest.mark.parametrize(
    ("options", "message"),
    [
        ({"levels": 0}, r"CommandCurriculum.levels must be a whole number in 1..1000, got 0"),
        ({"tolerance": (0.1, -1)}, r"CommandCurriculum.tolerance must be two numbers > 0"),
        ({"vx": (1.0, 0.0)}, r"CommandCurriculum.vx"),
    ],
)
def test_a_curriculum_setting_out_of_range_is_refused_naming_it(options, message):
    with pytest.raises(ValueError, match=message):
        terms.CommandCurriculum(**options)


def test_joystick_training_starts_at_the_curriculums_first_level_and_logs_it(tmp_path):
    with Trainer("quadrupeds:go2_joystick", out_dir=tmp_path, **TINY) as trainer:
        trainer.learn(TINY["num_envs"] * TINY["rollout_length"], progress_bar=False)
        states = [state["team"]["task"] for state in trainer.env.get_state()]
    rows = list(csv.DictReader((tmp_path / "metrics.csv").open()))
    assert [float(row["command_level"]) for row in rows] == [0.0]  # no command judged yet
    for state in states:  # WALK's forward band, or standing; level 0
        command = state["command"]
        assert state["curriculum"]["level"] == 0
        assert (command == 0).all() or (0.3 <= command[0] <= 1.0 and (command[1:] == 0).all())


def test_a_saved_episode_with_a_value_it_could_not_have_saved_is_refused_and_nothing_changes():
    def joystick(seed):
        team = envs.make_team("quadrupeds:go2_joystick", seed=seed, randomize=True)
        team.reset(seed=seed)
        for _ in range(20):
            team.advance(np.random.default_rng(seed).uniform(-1, 1, (4, 3)))
        return team

    saved, other = joystick(0).get_state(), joystick(1)
    before = other.get_state()
    size, task = saved["physics"].size, saved["task"]
    (rhythm,) = [key for key in task["memory"] if key.startswith("phase_time")]
    cases = {
        rf"physics state must be {size} finite numbers .* got shape \({size - 3},\)": {
            "physics": saved["physics"][:-3]
        },
        r"physics state .* largest \|value\| nan": {"physics": saved["physics"] * np.nan},
        r"geom placement .* largest \|value\| inf": {"geom_pos": saved["geom_pos"] + np.inf},
        r"step count must be a whole number in 0..1000, got -5": {"steps": -5},
        r"step count must be a whole number in 0..1000, got 1.5": {"steps": 1.5},
        r"start pose must be 2 finite numbers": {"start": [np.zeros(5), saved["start"][1]]},
        r"random stream must be numpy's generator state": {"random": ("MT19937", 5)},
        r"command must be 3 finite numbers within \+-10 .* largest \|value\| 1e\+09": {
            "task": {**task, "command": np.array([1e9, 0.0, 0.0])}
        },
        r"previous action must be 12 finite numbers within \+-1": {
            "task": {**task, "previous_action": np.full(12, np.nan)}
        },
        r"command age \(steps\) must be a whole number >= 0, got -3": {
            "task": {**task, "command_age": -3}
        },
        rf"term memory '{rhythm}' must be 8 finite numbers .* got shape \(3,\)": {
            "task": {**task, "memory": {**task["memory"], rhythm: np.zeros(3)}}
        },
        r"fall flag must be True or False, got 'no'": {"task": {**task, "fell": "no"}},
        r"term memory 'x' holds 100000 numbers, past the 4096": {
            "task": {**task, "memory": {"x": np.zeros(100_000)}}
        },
        # every other value taken, the randomizer's refused: the physics set before it undone
        r"mass must be 14 numbers within": {
            "randomizer": {
                **saved["randomizer"],
                "draws": {**saved["randomizer"]["draws"], "mass": np.full(14, 1e9)},
            }
        },
    }
    for message, change in cases.items():
        with pytest.raises(ValueError, match=message):
            other.set_state({**saved, **change})
        now = other.get_state()
        np.testing.assert_array_equal(now["physics"], before["physics"])
        np.testing.assert_array_equal(now["task"]["command"], before["task"]["command"])
        assert now["steps"] == before["steps"]
    other.set_state(saved)  # what an env saved itself is taken
    np.testing.assert_array_equal(other.get_state()["physics"], saved["physics"])
