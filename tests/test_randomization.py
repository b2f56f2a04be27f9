"""Domain randomization: each factor changes what it should, only when on; draws come from the
env's seeded stream (same episodes at any worker count, exact resume); bad settings are
refused naming the factor."""

from __future__ import annotations

import re

import numpy as np
import pytest
import torch
from click.testing import CliRunner
from helpers import TINY, trained_like
from pettingzoo.test import parallel_api_test

from mat_sdk import envs
from mat_sdk.cli import main
from mat_sdk.envs import Randomization, Trusted
from mat_sdk.training.trainer import Trainer
from tests.recipes import with_examples

with_examples()

GO2 = "go2:walk"
MODEL_FIELDS = ("geom_friction", "body_mass", "body_inertia", "body_ipos", "actuator_gainprm",
                "actuator_biasprm", "dof_damping", "dof_armature")  # fmt: skip


def _only(**factors) -> dict:
    return {"defaults": False, **factors}


def _model_values(team) -> dict[str, np.ndarray]:
    model = team.physics.model.ptr
    return {name: getattr(model, name).copy() for name in MODEL_FIELDS}


def _changed(factors: dict, seed: int = 1) -> set[str]:
    """The model fields an episode under `factors` changes from the plain robot's."""
    plain, randomized = (
        envs.make_team(GO2, seed=seed),
        envs.make_team(GO2, seed=seed, randomize=_only(**factors)),
    )
    plain.reset(), randomized.reset()
    before, after = _model_values(plain), _model_values(randomized)
    return {name for name in MODEL_FIELDS if not np.array_equal(before[name], after[name])}


@pytest.mark.parametrize(
    ("factors", "fields"),
    [
        ({"friction": [0.5, 1.25]}, {"geom_friction"}),
        ({"mass": [0.9, 1.1]}, {"body_mass", "body_inertia"}),
        ({"payload": [1.0, 2.0]}, {"body_mass"}),
        ({"com": 0.02}, {"body_ipos"}),
        ({"strength": [0.8, 1.2]}, {"actuator_gainprm", "actuator_biasprm"}),
        ({"damping": [0.8, 1.2]}, {"dof_damping"}),
        ({"armature": [0.8, 1.2]}, {"dof_armature"}),
        ({}, set()),
    ],
    ids=["friction", "mass", "payload", "com", "strength", "damping", "armature", "none"],
)
def test_each_model_factor_changes_its_own_fields_only(factors, fields):
    assert _changed(factors) == fields


def test_model_factors_scale_the_models_own_values_within_their_ranges():
    plain = envs.make_team(GO2, seed=0)
    team = envs.make_team(
        GO2, seed=0, randomize=_only(friction=[0.5, 0.6], payload=[1.5, 2.0], strength=[1.1, 1.2])
    )
    nominal = _model_values(plain)
    base = team._randomizer._base
    for episode in range(5):
        team.reset(seed=episode)
        model = team.physics.model.ptr
        scale = model.geom_friction / nominal["geom_friction"]
        assert np.allclose(scale, scale[0, 0]) and 0.5 <= scale[0, 0] <= 0.6  # one global scale
        added = model.body_mass[base] - nominal["body_mass"][base]
        assert 1.5 <= added <= 2.0
        kp = model.actuator_biasprm[:, 1] / nominal["actuator_biasprm"][:, 1]
        assert np.allclose(model.actuator_gainprm[:, 0] / nominal["actuator_gainprm"][:, 0], kp)
        assert ((kp >= 1.1) & (kp <= 1.2)).all()  # a position actuator's kp, in gain and bias
        # the bias's damping term is the model's own
        assert np.array_equal(model.actuator_biasprm[:, 2], nominal["actuator_biasprm"][:, 2])
    team.reset(seed=0)
    off = envs.make_team(GO2, seed=0, randomize=False)
    off.reset(seed=0)
    assert all(np.array_equal(v, nominal[k]) for k, v in _model_values(off).items())


def test_per_geom_friction_draws_one_scale_per_geom_within_the_range():
    nominal = _model_values(envs.make_team(GO2, seed=0))["geom_friction"][:, 0]
    team = envs.make_team(GO2, seed=0, randomize=_only(friction=[0.5, 1.5], per_geom_friction=True))
    team.reset(seed=3)
    scale = team.physics.model.ptr.geom_friction[:, 0] / nominal
    assert ((scale >= 0.5) & (scale <= 1.5)).all()
    assert np.ptp(scale) > 0.2  # the geoms differ, where the global scale gives them one


def test_latency_delays_the_action_the_motors_get_by_k_steps():
    team = envs.make_team(GO2, seed=0, randomize=_only(latency=[2, 2]))
    plain = envs.make_team(GO2, seed=0)
    team.reset(), plain.reset()
    ctrl = team.physics.data.ctrl
    home_ctrl = plain.actions.targets.targets(np.zeros(12))
    actions = [np.full((4, 3), value) for value in (0.3, -0.2, 0.1, 0.4)]
    sent = []
    for action in actions:
        team.advance(action)
        sent.append(ctrl.copy())
    assert np.allclose(sent[0], home_ctrl) and np.allclose(sent[1], home_ctrl)
    assert np.allclose(sent[2], plain.actions.targets.targets(actions[0].reshape(-1)))
    assert np.allclose(sent[3], plain.actions.targets.targets(actions[1].reshape(-1)))
    # what the agents observe as their previous action is what they sent, not what arrived
    last = team.wiring().observation.source["last_action"]
    assert np.allclose(team.observations.source()[last[0] : last[1]], 0.4)


def test_observation_noise_is_in_each_signals_units_and_only_on_the_sensed_observation():
    team = envs.make_team(GO2, seed=0, randomize=_only(noise={"joint_pos": 0.01, "gyro": 0.2}))
    sensed = team.reset()
    clean = team.observe()
    difference = np.abs(sensed - clean)
    features = {f.name: slice(f.start, f.stop) for f in team.wiring().observation.features}
    assert 0 < difference[:, features["joints.pos"]].max() <= 0.01
    assert 0.01 < difference[:, features["gyro"]].max() <= 0.2
    assert difference[:, features["joints.vel"]].max() == 0  # no noise on unnamed signals
    assert difference[:, features["contacts"]].max() == 0
    plain = envs.make_team(GO2, seed=0)
    assert np.array_equal(plain.reset(), plain.observe())


def test_pushes_kick_the_base_and_start_noise_moves_the_joints():
    pushed = envs.make_team(GO2, seed=0, randomize=_only(push=1.0, push_every=[0.1, 0.1]))
    plain = envs.make_team(GO2, seed=0)
    pushed.reset(), plain.reset()
    for _ in range(4):
        pushed.advance(np.zeros((4, 3))), plain.advance(np.zeros((4, 3)))
    speed = [np.abs(t.physics.data.qvel[:2]).max() for t in (pushed, plain)]
    assert speed[0] > 0.2 > speed[1]
    started = envs.make_team(GO2, seed=0, randomize=_only(start=0.05))
    plain.reset(seed=4), started.reset(seed=4)
    shift = np.abs(started.physics.data.qpos[7:] - plain.physics.data.qpos[7:])
    assert 0 < shift.max() <= 0.05 + 1e-12


def test_a_randomized_episode_resumes_exactly_from_its_state():
    team = envs.make_team(GO2, seed=2, randomize=True)
    rng = np.random.default_rng(0)
    team.reset()
    for _ in range(30):
        team.advance(rng.uniform(-1, 1, (4, 3)))
    state = team.get_state()
    actions = rng.uniform(-1, 1, (40, 4, 3))
    straight = [team.advance(a)[0] for a in actions]
    other = envs.make_team(GO2, seed=9, randomize=True)
    other.reset()
    other.set_state(state)
    again = [other.advance(a)[0] for a in actions]
    np.testing.assert_array_equal(np.array(straight), np.array(again))
    draws = state["randomizer"]["draws"]  # the episode's robot, factor by factor
    assert {"friction", "mass", "payload", "strength", "damping"} <= set(draws)
    tampered = {**state, "randomizer": {**state["randomizer"], "draws": {**draws, "gravity": 2}}}
    with pytest.raises(ValueError, match=r"unknown factor\(s\) \['gravity'\]"):
        other.set_state(tampered)
    unpushable = {**state, "randomizer": {**state["randomizer"], "next_push": float("nan")}}
    with pytest.raises(ValueError, match=r"next push time must be a number, got nan"):
        other.set_state(unpushable)


def test_a_saved_robot_this_randomization_could_not_draw_is_refused_untouched():
    team = envs.make_team(GO2, seed=2, randomize=_only(mass=(0.9, 1.1), latency=(1, 1)))
    team.reset()
    team.advance(np.zeros((4, 3)))
    saved = team.get_state()["randomizer"]
    other = envs.make_team(GO2, seed=3, randomize=_only(mass=(0.9, 1.1), latency=(1, 1)))
    other.reset()
    before = other.get_state()
    masses = other.physics.model.body_mass.copy()
    mass = saved["draws"]["mass"]
    cases = {
        r"mass must be 14 numbers within \[0.9, 1.1\], got \[.*e\+0[89]": {"mass": mass * 1e9},
        r"mass must be 14 numbers within .* \(shape \(3,\)\)": {"mass": mass[:3]},
        r"mass must be .* got \[nan": {"mass": np.full_like(mass, np.nan)},
        r"draws friction, which this one leaves off": {"friction": np.ones(1)},
        r"latency must lie in 1..1 control steps, got 1000000": {"latency": 1e6},
        r"latency must be a whole number of control steps, got nan": {"latency": float("nan")},
        r"latency must be a whole number of control steps, got 1.5": {"latency": 1.5},
    }
    for message, change in cases.items():
        state = {**before, "randomizer": {**saved, "draws": {**saved["draws"], **change}}}
        with pytest.raises(ValueError, match=message):
            other.set_state(state)
    late = saved["pending"]
    assert len(late) == 1
    for message, pending in {
        r"holds 3 late actions; its latency of 1 control steps holds 0 or 1": late * 3,
        r"late action must be 12 finite numbers within \+-1 \(shape \(12,\)\), got shape "
        r"\(12,\), largest \|value\| [56]": [late[0] + 5.0],
        r"late action must be 12 finite numbers within \+-1 \(shape \(12,\)\), got shape "
        r"\(3,\)": [late[0][:3]],
    }.items():  # fmt: skip
        with pytest.raises(ValueError, match=message):
            other.set_state({**before, "randomizer": {**saved, "pending": pending}})
    np.testing.assert_array_equal(other.physics.model.body_mass, masses)  # nothing applied
    other.set_state({**before, "randomizer": saved})  # what it drew itself is taken


def test_same_seed_same_randomized_episodes_at_any_worker_count():
    def run(workers):
        with envs.make_vec(GO2, num_envs=3, workers=workers, seed=5, episode_limit=15,
                           randomize=True) as vec:  # fmt: skip
            trace = [vec.reset()]
            rng = np.random.default_rng(0)
            for _ in range(35):
                obs, reward, *_ = vec.step(rng.uniform(-1, 1, (3, 4, 3)))
                trace += [obs.reshape(-1), reward]
            return np.concatenate([np.ravel(t) for t in trace])

    local, two = run(0), run(2)
    assert np.array_equal(local, two)
    other_seed = envs.make_vec(GO2, num_envs=3, seed=6, randomize=True)
    assert not np.array_equal(other_seed.reset().reshape(-1), local[: other_seed.reset().size])


def test_a_randomized_env_passes_pettingzoos_parallel_api_test():
    parallel_api_test(envs.make(GO2, seed=0, randomize=True), num_cycles=40)


def test_a_randomized_training_run_resumes_exactly_and_records_its_randomization(tmp_path):
    randomize = {"latency": [0, 2], "push_every": [0.2, 0.4]}
    options = {**TINY, "num_envs": 2, "rollout_length": 20, "env_options": {"randomize": randomize}}
    with Trainer(GO2, out_dir=tmp_path / "a", **options) as trainer:
        trainer.learn(40, progress_bar=False)
        trainer.save(tmp_path / "half.pt")
        trainer.learn(80, progress_bar=False)
        straight = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
    with Trainer.load(Trusted(tmp_path / "half.pt"), out_dir=tmp_path / "b") as again:
        assert again.config.env.options["randomize"]["latency"] == [0, 2]
        again.learn(80, progress_bar=False)
        for name, value in again.policy.state_dict().items():
            assert np.array_equal(value.numpy(), straight[name].numpy()), name


def test_from_mjcf_takes_a_randomization_and_the_env_option_overrides_it():
    import go2

    spec = envs.from_mjcf(
        go2.MODELS / "scene_mjx.xml", go2.LAYOUT, go2.REWARD, observation=go2.walk().observation,
        randomize={"payload": [0.5, 1.0]}, commands=go2.WALK,
    )  # fmt: skip
    assert spec.build().randomization.payload == (0.5, 1.0)
    assert spec.build(randomize=False).randomization is None
    assert spec.build(randomize={"defaults": False, "mass": [1, 1.1]}).randomization.payload is None
    assert Randomization.parse(Randomization().to_dict()) == Randomization()


@pytest.mark.parametrize(
    ("given", "message"),
    [
        ({"frction": [0.5, 1]}, r"no factor\(s\) \['frction'\]; its factors: friction"),
        (
            {"friction": [1.2, 0.5]},
            "friction must be \\[low, high\\], two finite numbers with low <= high",
        ),
        ({"friction": 0.5}, "friction must be \\[low, high\\], two finite numbers with"),
        ({"friction": [0, 1]}, "friction must be \\[low, high\\] with 0 < low"),
        ({"latency": [0, 1.5]}, "latency is \\[low, high\\] control steps, whole numbers"),
        ({"push": -1}, "push must be a number in \\[0, 5\\] or null"),
        ({"noise": {"joint_pos": "high"}}, "noise maps signal names to levels"),
        ({"noise": {"lidar": 0.1}}, r"noise names signal\(s\) \['lidar'\].*its signals: joint_pos"),
        ({"payload": [-20, 0]}, "payload \\[-20, 0\\] would leave the base"),
        ("lots", "randomize is true, false, or a mapping of factors"),
        ({"defaults": "no"}, "randomize defaults must be true or false"),
    ],
)
def test_bad_randomizations_are_refused_naming_the_factor(given, message):
    with pytest.raises(ValueError, match=message):
        envs.make_team(GO2, randomize=given)


def test_the_checkpoint_and_the_bundle_record_the_randomization(tmp_path):
    from mat_export import export
    from mat_runtime import Policy

    with Trainer(GO2, **{**TINY, "env_options": {"randomize": {"payload": [0, 1]}}}) as trainer:
        trainer.learn(20, progress_bar=False)
        checkpoint = trainer.save(tmp_path / "go2.pt")
    export(Trusted(checkpoint), tmp_path / "onnx", agent_counts=(4,))
    recorded = Policy.load(tmp_path / "onnx").randomization
    assert Randomization.parse(recorded) == Randomization(payload=(0.0, 1.0))
    with Trainer(GO2, **TINY) as plain:
        plain.learn(20, progress_bar=False)
        saved = torch.load(plain.save(tmp_path / "plain.pt"), weights_only=True)
    assert saved["config"]["env"]["randomization"] is None


def test_mamujoco_robots_take_the_same_randomization_and_resume_exactly():
    plain = envs.make_team("mamujoco:Ant-4x2", seed=0)
    team = envs.make_team("mamujoco:Ant-4x2", seed=0, randomize={"noise": {"obs": 0.01}})
    model = team._env.single_agent_env.unwrapped.model
    nominal = plain._env.single_agent_env.unwrapped.model.body_mass.copy()
    team.reset(), plain.reset()
    assert not np.array_equal(model.body_mass, nominal)  # masses and the payload on the torso
    rng = np.random.default_rng(0)
    for _ in range(20):
        team.advance(rng.uniform(-1, 1, (4, 2)))
    state = team.get_state()
    actions = rng.uniform(-1, 1, (30, 4, 2))
    straight = [team.advance(a)[0] for a in actions]
    other = envs.make_team("mamujoco:Ant-4x2", seed=7, randomize={"noise": {"obs": 0.01}})
    other.reset()
    other.set_state(state)
    np.testing.assert_array_equal(np.array(straight), [other.advance(a)[0] for a in actions])
    parallel_api_test(envs.make("mamujoco:HalfCheetah-6x1", seed=0, randomize=True), num_cycles=20)


@pytest.fixture(scope="module")
def go2_checkpoint(tmp_path_factory):
    path = tmp_path_factory.mktemp("sweep") / "go2.pt"
    with Trainer(GO2, **{**TINY, "env_options": {"episode_limit": 30}}) as trainer:
        trainer.learn(20, progress_bar=False)
        trained_like(trainer.policy)  # unit-gain weights: actions that differ visibly
        return trainer.save(path)


def test_mat_eval_sweeps_one_factor_and_plots_it(go2_checkpoint, tmp_path):
    plot = tmp_path / "latency.png"
    result = CliRunner().invoke(main, [
        "eval", str(go2_checkpoint), "--sweep", "latency=0,2", "--episodes", "2",
        "--plot", str(plot), "--trust-env-code",
    ])  # fmt: skip
    assert result.exit_code == 0, result.output
    rows = re.findall(r"^\| (\d+) \| ([-\d,.]+) ± [\d,.]+ \| (\d) / 2 \| ([\d.]+) ±", result.output,
                      re.MULTILINE)  # fmt: skip
    assert [row[0] for row in rows] == ["0", "2"]
    assert rows[0][1] != rows[1][1]  # two steps late, the same policy does differently
    assert plot.stat().st_size > 10_000


@pytest.mark.parametrize(
    ("arguments", "message"),
    [
        (["--sweep", "frction=0.4,1"], "cannot sweep 'frction'; sweepable factors: friction"),
        (["--sweep", "latency"], "'latency': use FACTOR=VALUES"),
        (["--sweep", "payload=0:2"], "sweep values '0:2': give low:high:count"),
        (["--plot", "x.png"], "--plot draws a sweep or a grid: give --sweep or --grid too"),
        (["--sweep", "payload=0,1", "--fault", "FR_hip_joint=zero"], "drop --fault"),
    ],
)
def test_bad_sweeps_get_one_line_naming_the_problem(go2_checkpoint, arguments, message):
    result = CliRunner().invoke(main, ["eval", str(go2_checkpoint), "--trust-env-code", *arguments])
    assert result.exit_code != 0 and message in result.output, result.output
    assert "Traceback" not in result.output


def test_strength_randomization_scales_a_weak_motor_from_its_weakened_force():
    plain = envs.make_team(GO2, seed=0)
    weak = envs.make_team(
        GO2, seed=0, faults={"FR_calf_joint": "weak:0.5"}, randomize=_only(strength=[1.1, 1.2])
    )
    weak.reset(seed=0)
    knee = plain.physics.model.ptr.actuator("FR_calf").id
    nominal = plain.physics.model.ptr.actuator_gainprm[:, 0]
    scale = weak.physics.model.ptr.actuator_gainprm[:, 0] / nominal
    assert 0.55 <= scale[knee] <= 0.6  # 0.5 x a draw in 1.1-1.2
    assert ((np.delete(scale, knee) >= 1.1) & (np.delete(scale, knee) <= 1.2)).all()
