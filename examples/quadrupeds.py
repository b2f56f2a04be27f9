"""Three quadrupeds, one task: the SDK's `legged.WALK` on the Unitree Go2 (15 kg), the
Unitree A1 (12.5 kg) and Boston Dynamics Spot (50.3 kg), one agent per leg.

    PYTHONPATH=examples mat train quadrupeds:spot --seeds 3 --steps 2000000 --out runs/spot
    PYTHONPATH=examples mat train quadrupeds:go2_joystick --steps 2000000   # any command

Only names differ per robot: the layout (which actuators each leg drives), the feet, the
IMU and the trunk, and where an episode starts. The A1 starts from joint angles (`start=`,
its keyframe ignored) to show a model without a keyframe; the others from their `home`
keyframe. The terms, weights, command, termination, randomization and the training recipe
are `legged.WALK`'s, unchanged (docs/REAL_ROBOTS.md, "One task, any legged robot").

`robots/` holds trimmed copies of MuJoCo Menagerie's models (collision geometry only; each
folder says what was removed and under which licence); the full models work the same.
"""

from pathlib import Path

from mat_sdk.envs.tasks.legged import JOYSTICK, WALK, LeggedRobot

ROBOTS = Path(__file__).parent / "robots"
LEGS = ("FL", "FR", "RL", "RR")  # front left, front right, rear left, rear right

GO2 = LeggedRobot(
    ROBOTS / "unitree_go2" / "scene_mjx.xml",
    layout={leg: [f"{leg}_hip", f"{leg}_thigh", f"{leg}_calf"] for leg in LEGS},
    feet=LEGS,  # foot geoms named after their legs
    imu="imu",  # a site
    trunk=("base",),
)
A1 = LeggedRobot(
    ROBOTS / "unitree_a1" / "scene.xml",
    layout={leg: [f"{leg}_hip", f"{leg}_thigh", f"{leg}_calf"] for leg in LEGS},
    feet=tuple(f"{leg}_calf" for leg in LEGS),  # the foot geoms are unnamed: their bodies
    imu="trunk",  # no IMU site: the trunk body's frame
    trunk=("trunk",),
    start={f"{leg}_{joint}_joint": angle for leg in LEGS
           for joint, angle in (("hip", 0.0), ("thigh", 0.9), ("calf", -1.8))},
)  # fmt: skip
SPOT = LeggedRobot(
    ROBOTS / "boston_dynamics_spot" / "scene.xml",
    layout={leg: [f"{leg.lower()}_hx", f"{leg.lower()}_hy", f"{leg.lower()}_kn"]
            for leg in ("FL", "FR", "HL", "HR")},  # hind legs: HL, HR
    feet=("FL", "FR", "HL", "HR"),
    imu="body",
    trunk=("body",),
)  # fmt: skip


def go2():
    return WALK.spec(GO2)


def a1():
    return WALK.spec(A1)


def spot():
    return WALK.spec(SPOT)


def go2_joystick():
    """`legged.JOYSTICK`: any velocity command in range, standing included, changing every 5 s."""
    return JOYSTICK.spec(GO2)


def a1_joystick():
    return JOYSTICK.spec(A1)


def spot_joystick():
    return JOYSTICK.spec(SPOT)


def go2_task_on_spot():
    """The Go2's own task (`go2.py`: penalties in the Go2's units) on Spot, names alone
    changed, as a new user would first try it: for comparison in docs/REAL_ROBOTS.md."""
    import go2

    from mat_sdk import envs

    return envs.from_mjcf(
        SPOT.model, SPOT.layout, [*go2.REWARD[:-1], go2.terms.FeetAirTime(1.0, SPOT.feet)],
        terminate=[go2.terms.Tilt(60.0), go2.terms.IllegalContact(SPOT.trunk)],
        commands=go2.WALK, actions=envs.JointTargets(scale=0.5), substeps=10,
        episode_limit=1000, root_noise=(0.0, 0.05),
        observation=envs.Observation(imu=SPOT.imu, contacts=SPOT.feet, last_action=True),
    )  # fmt: skip
