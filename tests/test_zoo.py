"""The model zoo: every model is listed, reproduces its card, and serves without torch."""

import json
import subprocess
import sys

import numpy as np
import pytest

from mat_runtime import BundleError, Policy
from mat_runtime.zoo import models, zoo_dir
from mat_sdk.envs import Trusted
from mat_sdk.evaluation.episodes import CheckpointPolicy, evaluate
from mat_sdk.policy import checkpoint

MODELS = models()


def _card(name):
    return json.loads((zoo_dir() / name / "card.json").read_text())


def test_the_zoo_has_models_and_mat_zoo_lists_them():
    assert MODELS, f"no models in {zoo_dir()}"
    out = subprocess.run(
        [sys.executable, "-m", "mat_sdk", "zoo"], capture_output=True, text=True, check=True
    ).stdout
    for name in MODELS:
        assert f"| zoo:{name} | {_card(name)['env_id']} |" in out, out


@pytest.mark.parametrize(
    "name",  # one model in the default suite, every card with `pytest -m slow`
    [
        pytest.param(n, marks=[] if n == "swimmer-family-mat" else [pytest.mark.slow])
        for n in MODELS
    ],
)
def test_a_zoo_model_reproduces_its_card_far_above_a_random_team(name):
    """As `mat eval zoo:NAME --episodes N`: the same starts and batch, so the same returns up
    to the float differences between CPUs (which a long episode can amplify)."""
    from tests.recipes import with_examples

    with_examples()  # an example's robot (go2-walk-mat: quadrupeds:go2)
    card = _card(name)
    score = card["return"]
    loaded = CheckpointPolicy.from_checkpoint(Trusted(f"zoo:{name}"))  # ours
    returns = evaluate(loaded, score["episodes"], seed=score["evaluation_seed"])
    assert abs(np.mean(returns) - score["mean"]) <= max(0.05 * abs(score["mean"]), 1.0)
    random = card["random_team_return"]
    assert np.mean(returns) > random + 0.5 * (score["mean"] - random) > random + 10


@pytest.mark.parametrize("name", MODELS)
def test_a_zoo_bundle_serves_without_torch(name):
    script = (
        "import sys; sys.modules['torch'] = None\n"
        "import numpy as np\n"
        "from mat_runtime import Policy\n"
        f"policy = Policy.load('zoo:{name}')\n"
        "counts = (2, 5, 9) if policy.max_agents is None else (policy.max_agents,)  # MAPPO\n"
        "for n in counts:\n"
        "    assert policy.act(np.zeros((n, policy.obs_dim))).shape == (n, policy.action_size)\n"
        "print(policy.env_id)\n"
    )
    out = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True)
    assert out.returncode == 0 and _card(name)["env_id"] in out.stdout, out.stderr


@pytest.mark.slow
def test_a_zoo_model_fine_tunes(tmp_path):
    name = MODELS[0]
    run = subprocess.run(
        [sys.executable, "-m", "mat_sdk", "finetune", f"zoo:{name}", "--steps", "400",
         "--episodes", "1", "--set", "num_envs=4", "--out", str(tmp_path / "tuned"), "--quiet"],
        capture_output=True, text=True,
    )  # fmt: skip
    assert run.returncode == 0, run.stderr
    assert checkpoint.load(tmp_path / "tuned" / "checkpoint.pt")["progress"]["steps"] >= 400


def test_zoo_names_that_are_not_there_or_not_names_are_refused():
    with pytest.raises(checkpoint.CheckpointError, match="no zoo model 'nope' in .*the zoo has"):
        checkpoint.load("zoo:nope")
    with pytest.raises(BundleError, match="a zoo name is letters, digits"):
        Policy.load("zoo:../escape")
