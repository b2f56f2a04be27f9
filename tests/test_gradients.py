"""Update workers: a minibatch's gradient split over processes is the same gradient, and a
worker that fails or dies is reported, not waited on."""

import pytest
import torch
from helpers import TINY

from mat_sdk.training.ppo import Rows
from mat_sdk.training.trainer import Trainer

SPLIT = {**TINY, "ppo_epochs": 2, "num_minibatches": 2, "shuffle_agents": True}


def shared_rows(trainer: Trainer) -> Rows:
    """A rollout's batch as rows, shared with the trainer's update workers."""
    batch = trainer.rollout().rows()
    trainer.gradients.share(batch)
    return batch


def _train_hopper(**options):
    with Trainer("hopper-4x1", "mat", **SPLIT, **options) as trainer:
        start = {k: v.clone() for k, v in trainer.policy.state_dict().items()}
        trainer.learn(60, progress_bar=False)  # 3 updates of 4 optimizer steps
        return start, trainer.policy.state_dict()


@pytest.mark.parametrize(
    "options",
    [
        {"update_workers": 1},
        pytest.param({"update_workers": 1, "compile": True}, marks=pytest.mark.slow),
    ],
    ids=["eager", "compiled"],
)
def test_a_split_update_trains_like_one_process(options):
    start, one = _train_hopper()
    moved = max(float((one[k] - start[k]).abs().max()) for k in start)
    assert moved > 1e-4  # the comparison below means something
    _, split = _train_hopper(**options)
    for name in one:
        assert torch.allclose(one[name], split[name], rtol=0, atol=1e-6), (options, name)


def test_update_worker_errors_are_reported_with_their_cause():
    with Trainer("hopper-4x1", "mat", update_workers=1, **TINY) as trainer:
        batch = shared_rows(trainer)
        rows = torch.tensor([0, 1, 2, 10_000])  # the worker's share holds the bad row
        targets = batch.returns[:4]
        with pytest.raises(RuntimeError, match="update worker failed") as error:
            trainer.gradients.backward(rows, targets)
        assert "IndexError" in str(error.value)
        with pytest.raises(RuntimeError, match="closed"):
            trainer.gradients.start()

    with Trainer("hopper-4x1", "mat", update_workers=1, **TINY) as trainer:
        batch = shared_rows(trainer)
        trainer.gradients._workers[0].process.kill()
        with pytest.raises(RuntimeError, match="a worker process died"):
            trainer.gradients.backward(torch.arange(4), batch.returns[:4])


def test_update_workers_need_rows_to_split():
    """Refused where the config is made, before any env or update worker starts."""
    with pytest.raises(ValueError, match="a minibatch of 20 env-steps cannot be split 21"):
        Trainer("hopper-4x1", "mat", update_workers=20, **TINY)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a GPU")
def test_update_workers_are_refused_on_a_gpu():
    with pytest.raises(ValueError, match="update_workers splits CPU updates"):
        Trainer("hopper-4x1", "mat", update_workers=1, device="cuda", **TINY)
