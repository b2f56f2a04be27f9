"""A normal (non-editable) install maps the three folders to their import names."""

import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parent.parent


def test_normal_install_imports_all_three_packages(tmp_path):
    target = tmp_path / "site"
    subprocess.run(
        [
            sys.executable,
            "-m",
            "pip",
            "install",
            "-q",
            "--no-deps",
            "--no-build-isolation",
            "--target",
            str(target),
            str(ROOT),
        ],
        check=True,
        capture_output=True,
    )
    code = (
        "import mat_sdk, mat_runtime, mat_export, mat_sdk.envs, mat_sdk.bench, "
        "mat_sdk.training.trainer, mat_sdk.evaluation.tracking; "
        "print(mat_sdk.__file__); print(mat_runtime.__file__); print(mat_export.__file__)"
    )
    # The installed copy must win over the source tree: run from elsewhere, target first.
    env = {"PYTHONPATH": str(target), "PATH": "/usr/bin:/bin"}
    result = subprocess.run(
        [sys.executable, "-c", code],
        cwd=tmp_path,
        env=env,
        capture_output=True,
        text=True,
        check=True,
    )
    files = result.stdout.split()
    assert len(files) == 3 and all(f.startswith(str(target)) for f in files), result.stdout
    # every module of the source tree is in the wheel: no subpackage left out of pyproject's list
    source = Path(__file__).resolve().parents[1] / "mat_sdk"
    missing = [
        str(f.relative_to(source))
        for f in source.rglob("*.py")
        if not (target / "mat_sdk" / f.relative_to(source)).exists()
    ]
    assert not missing, missing
