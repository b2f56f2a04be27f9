"""Memory per env copy of a textured robot: physics copies compiled with their visual assets
(textures, visual meshes) against lean ones (`compiler.discardvisual`, what the SDK builds).

    python -m benchmarks.env_memory --copies 32 --texture-mb 240

The model is the trimmed Go2 with textures added on a visual-only geom, as a Menagerie model
with its textures carries them (the full Spot model: about 244 MB). Each variant runs in a
fresh process that builds `--copies` teams and reports its resident memory after the first
copy and after the last: the difference over copies - 1 is the memory per copy beyond the
first.
"""

from __future__ import annotations

import json
import subprocess
import sys
import tempfile
from pathlib import Path

import click

EXAMPLES = Path(__file__).resolve().parents[1] / "examples"

MEASURE = """
import json, sys
sys.path.insert(0, {examples!r})
from mat_sdk.envs.mujoco import model_task
from mat_sdk import envs
import quadrupeds
from mat_sdk.envs.tasks.legged import WALK, LeggedRobot

def rss_mb():
    return int(open("/proc/self/statm").read().split()[1]) * 4096 / 2**20

visual = {visual}
if visual:  # compile as before the lean copies: every asset kept
    original = model_task.compiled_model
    model_task.compiled_model = lambda source, _visual: original(source, True)
robot = LeggedRobot({model!r}, quadrupeds.GO2.layout, quadrupeds.GO2.feet, "imu", ("base",))
spec = WALK.spec(robot)
teams = [spec.build(seed=0)]
first = rss_mb()
teams += [spec.build(seed=k) for k in range(1, {copies})]
last = rss_mb()
print(json.dumps({{"first": first, "last": last}}))
"""


def textured_go2(folder: Path, texture_mb: int) -> Path:
    """The trimmed Go2 with `texture_mb` of RGB textures on a visual-only geom."""
    source = EXAMPLES / "robots" / "unitree_go2"
    side = 2048
    count = max(1, round(texture_mb * 2**20 / (side * side * 3)))
    assets = "".join(
        f'<texture name="skin{k}" type="2d" builtin="checker" width="{side}" height="{side}" '
        f'rgb1="{k / count:.2f} .2 .2" rgb2=".9 .9 .9"/>'
        f'<material name="skin{k}" texture="skin{k}"/>'
        for k in range(count)
    )
    geoms = "".join(
        f'<geom type="sphere" size=".01" material="skin{k}" contype="0" conaffinity="0"/>'
        for k in range(count)
    )
    robot = (source / "go2_mjx.xml").read_text()
    robot = robot.replace("<asset>", f"<asset>{assets}", 1)
    marker = '<site name="imu"'
    robot = robot.replace(marker, f"{geoms}{marker}", 1)
    (folder / "go2_mjx.xml").write_text(robot)
    (folder / "scene.xml").write_text(
        (source / "scene_mjx.xml").read_text().replace("go2_mjx.xml", str(folder / "go2_mjx.xml"))
    )
    for mesh in (source / "assets").glob("*") if (source / "assets").exists() else []:
        (folder / "assets").mkdir(exist_ok=True)
        (folder / "assets" / mesh.name).write_bytes(mesh.read_bytes())
    return folder / "scene.xml"


@click.command()
@click.option("--copies", default=32, show_default=True, help="env copies per process")
@click.option("--texture-mb", default=240, show_default=True, help="MB of textures to add")
def main(copies: int, texture_mb: int) -> None:
    with tempfile.TemporaryDirectory() as folder:
        model = textured_go2(Path(folder), texture_mb)
        print(f"Go2 + {texture_mb} MB of textures, {copies} env copies per process")
        print("| physics copies | RSS after 1 copy (MB) | after all | per copy beyond the first |")
        print("|---|---|---|---|")
        for visual in (True, False):
            code = MEASURE.format(examples=str(EXAMPLES), visual=visual, model=str(model),
                                  copies=copies)  # fmt: skip
            run = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True)
            if run.returncode:
                sys.exit(run.stderr)
            result = json.loads(run.stdout.strip().splitlines()[-1])
            per_copy = (result["last"] - result["first"]) / max(copies - 1, 1)
            label = "with visual assets" if visual else "lean (discardvisual)"
            print(f"| {label} | {result['first']:.0f} | {result['last']:.0f} | {per_copy:.1f} |")


if __name__ == "__main__":
    main()
