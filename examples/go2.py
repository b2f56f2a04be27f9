"""A real robot as a MAT SDK env: MuJoCo Menagerie's Unitree Go2, one agent per leg.

    PYTHONPATH=examples mat train go2:walk --seeds 3 --steps 2000000 --out runs/go2  # its recipe

Each leg is an agent that drives its hip (abduction), thigh and calf. Episodes start from the
model's `home` keyframe; an action is a joint target around that pose; each agent observes
what the robot's own hardware measures: its joint encoders, the IMU (gravity's direction and
the angular velocity in the base's frame), the four foot contacts, the velocity command and
its own previous action. The reward follows the command (forward speed vx, sideways vy, yaw
rate) and asks for a steady, smooth gait; an episode ends when the trunk tilts past 60
degrees or touches the floor. docs/REAL_ROBOTS.md walks through every choice.

This is the Go2's own task, its penalties in the Go2's units (N m, m/s), as measured in
docs/REAL_ROBOTS.md sections 6-8. For any legged robot, the Go2 included, use the
robot-relative task in `quadrupeds.py` (`mat_sdk.envs.tasks.legged.WALK`).

`robots/unitree_go2/` is a trimmed copy of Menagerie's model (collision geometry only, its
BSD-3-Clause license beside it); the full model with meshes works the same.
"""

from pathlib import Path

from mat_sdk import envs
from mat_sdk.envs import legged, terms

MODELS = Path(__file__).parent / "robots" / "unitree_go2"
LEGS = ("FL", "FR", "RL", "RR")  # front left, front right, rear left, rear right
LAYOUT = {leg: [f"{leg}_hip", f"{leg}_thigh", f"{leg}_calf"] for leg in LEGS}
FEET = LEGS  # the foot geoms are named after their legs

REWARD = [
    terms.TrackVelocity(1.0),  # follow the commanded vx, vy
    terms.TrackYawRate(0.5),  # and yaw rate
    terms.Alive(0.25),  # falling ends the episode: staying up pays
    terms.Upright(1.0),
    terms.VerticalVelocity(1.0, relative=False),  # no bouncing, in (m/s)^2
    terms.RollPitchRate(0.05),
    terms.ActionRate(0.01),  # smooth targets
    terms.Torque(2e-4, relative=False),  # effort, in (N m)^2: the Go2's own units
    terms.JointLimits(1.0),  # off the mechanical stops
    terms.FeetAirTime(1.0, FEET),  # strides, not shuffles: what makes a gait emerge early
]
TERMINATE = [terms.Tilt(60.0), terms.IllegalContact(("base",))]
WALK = terms.VelocityCommand(vx=(0.3, 1.0))  # forward at 0.3-1 m/s, straight
CONTROL_HZ = 50
# legged.WALK's recipe: 32 envs x 100 steps, 5 x 4 minibatches, the learning rate adapted to
# a KL of 0.01 per leg, 5 s training episodes (docs/REAL_ROBOTS.md section 11: a gait that
# holds in under 1e6 env steps, where a constant 3e-4 and 20 s episodes needed 1.6e6)
WALK_RECIPE = legged.WALK.recipe


def walk() -> envs.RobotSpec:
    """Go2 (position actuators, Menagerie's go2_mjx.xml) walking at a commanded velocity."""
    return envs.from_mjcf(
        MODELS / "scene_mjx.xml",
        LAYOUT,
        REWARD,
        terminate=TERMINATE,
        commands=WALK,
        observation=envs.Observation(imu="imu", contacts=FEET, last_action=True),
        actions=envs.JointTargets(scale=0.5),
        substeps=round(1 / CONTROL_HZ / 0.002),  # the model's 2 ms physics step
        episode_limit=1000,  # 20 s
        root_noise=(0.0, 0.05),
        recipe=WALK_RECIPE,  # docs/REAL_ROBOTS.md sections 6 and 11
    )


def walk_torque() -> envs.RobotSpec:
    """The same task on the torque-motor model (Menagerie's go2.xml): the policy's joint
    targets become torques through a PD layer at the physics rate, as on the robot."""
    spec = walk()
    return envs.from_mjcf(
        MODELS / "scene.xml",
        LAYOUT,
        REWARD,
        terminate=TERMINATE,
        commands=WALK,
        observation=spec.observation,
        actions=envs.JointTargets(scale=0.5, kp=50.0, kd=0.5),
        substeps=round(1 / CONTROL_HZ / 0.002),
        episode_limit=1000,
        root_noise=(0.0, 0.05),
        recipe=WALK_RECIPE,
    )
