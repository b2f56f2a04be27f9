"""Every value a file or an option records is bounded where it is read: a tampered checkpoint,
manifest or `--set` never exhausts memory, hangs, breaks the simulation or makes the robot
act on non-finite numbers. Each case asserts the error's type and that its message names the
field; none echoes more than a short prefix of the value.

The bounds and their reasons are tabled in docs/REAL_ROBOTS.md ("Bounds on recorded values").
"""

from __future__ import annotations

import math

import pytest

from mat_sdk import envs
from mat_sdk.envs import terms
from mat_sdk.envs.mujoco.randomization import Randomization
from tests.recipes import with_examples

with_examples()
import go2  # noqa: E402  (examples/, put on the path just above)


def _go2(**options):
    return envs.make_team("go2:walk", seed=0, **options)


@pytest.mark.parametrize(
    ("factors", "names"),
    [
        ({"latency": [1e9, 1e9]}, "randomize latency"),
        ({"latency": [0, 10**6]}, "randomize latency"),
        ({"mass": [1e-300, 1e-300]}, "randomize mass must lie within"),
        ({"strength": [1e300, 1e300]}, "randomize strength must lie within"),
        ({"friction": [0.5, 1e30]}, "randomize friction must lie within"),
        ({"push": 1e30}, "randomize push must be a number in"),
        ({"com": 1e30}, "randomize com must be a number in"),
        ({"noise": {"qpos": 1e308}}, "randomize noise maps signal names"),
        ({"noise": {"gyro": 1e308}}, "randomize noise maps signal names"),
        ({"push_every": [-1, 1]}, "randomize push_every"),
        ({"payload_share": [0, 1e30]}, "randomize payload_share must lie within"),
    ],
)
def test_randomization_factors_are_bounded_when_parsed(factors, names):
    with pytest.raises(ValueError, match=names):
        Randomization.parse(factors)


def test_a_huge_value_is_never_echoed_whole():
    with pytest.raises(ValueError, match="randomize friction") as error:
        Randomization.parse({"friction": [0.5] * 2_000_000})
    assert len(str(error.value)) < 300


@pytest.mark.parametrize(
    ("factors", "names"),
    [
        ({"payload": [1e30, 1e30]}, "payload up to 1e\\+30 is more than 2x the robot's mass"),
        ({"payload": [-100.0, 0.0]}, "would leave the base .* with no mass"),
        ({"com": 0.45}, "com 0.45 m moves the centre of mass outside the base"),
        ({"latency": [0, 50], "defaults": False}, "more than 1 s of control"),
    ],
)
def test_factors_that_depend_on_the_robot_are_bounded_by_its_model(factors, names):
    """Payloads against the robot's mass, the centre of mass against the base's size and the
    latency against the control rate: refused when the env is built, before a step."""
    with pytest.raises(ValueError, match=names):
        _robot_with(factors)


def _robot_with(factors):
    """go2:walk at 50 Hz for most factors; at 25 Hz for latency, where 50 steps are 2 s."""
    if "latency" not in factors:
        return _go2(randomize=factors)
    spec = envs.from_mjcf(
        go2.MODELS / "scene_mjx.xml", go2.LAYOUT, go2.REWARD, terminate=go2.TERMINATE,
        commands=go2.WALK, substeps=20, randomize=factors,
    )  # fmt: skip
    return spec.build(seed=0)


@pytest.mark.parametrize(
    ("option", "value", "names"),
    [
        ("hops", 10**9, "hops must be an integer in 0..64"),
        ("hops", -1, "hops must be an integer in 0..64"),
        ("episode_limit", 10**18, "episode_limit must be an integer in 1..100,000"),
    ],
)
def test_env_options_are_bounded(option, value, names):
    with pytest.raises(ValueError, match=names):
        envs.make_team("hopper-2x2", **{option: value})


@pytest.mark.parametrize(
    ("make", "names"),
    [
        (lambda: terms.VelocityCommand(vx=(0.0, 1e308)), r"VelocityCommand.vx must lie within"),
        (lambda: terms.Tilt(math.nan), r"Tilt.degrees must be a number in \(0, 180\]"),
        (lambda: terms.Tilt("60"), r"Tilt.degrees must be a number"),
        (lambda: terms.TrackVelocity(1.0, sigma=0.0), r"TrackVelocity.sigma must be a finite"),
        (lambda: terms.Torque(math.inf), "torque: weight must be a finite number"),
        (lambda: terms.JointLimits(fraction=2.0), r"JointLimits.fraction must be in \(0, 1\]"),
        (lambda: terms.TrunkHeight(math.nan), "TrunkHeight.minimum must be a finite"),
        (lambda: terms.FeetAirTime(threshold=-1.0), "FeetAirTime.threshold must be"),
    ],
)
def test_terms_check_their_parameters_when_made(make, names):
    with pytest.raises(ValueError, match=names):
        make()


def test_a_command_option_out_of_range_is_refused():
    with pytest.raises(ValueError, match=r"command must be three finite numbers within \+-10"):
        _go2(command=[1e9, 0.0, 0.0])


def test_a_tracking_term_without_commands_is_refused_when_the_env_is_built():
    with pytest.raises(ValueError, match="reward term TrackVelocity follows a velocity command"):
        envs.from_mjcf(go2.MODELS / "scene_mjx.xml", go2.LAYOUT, [terms.TrackVelocity(1.0)])
