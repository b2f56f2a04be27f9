"""Flat parameters: the same steps as torch's clip and Adam, and torch's checkpoint layout."""

import copy

import torch
from torch import nn

from mat_sdk.training.flat_params import FlatParameters


def test_flat_clip_and_adam_match_torch_per_parameter_and_save_its_layout():
    torch.manual_seed(0)
    plain = nn.Sequential(nn.Linear(5, 7), nn.Tanh(), nn.Linear(7, 3))
    flat_model = copy.deepcopy(plain)
    settings = {"lr": 1e-2, "eps": 1e-5}
    plain_opt = torch.optim.Adam(
        [{"params": plain[0].parameters()}, {"params": plain[2].parameters(), "lr": 3e-2}],
        **settings,
    )
    flat = FlatParameters([list(flat_model[0].parameters()), list(flat_model[2].parameters())])
    flat_opt = torch.optim.Adam(
        [{"params": [flat.buffers[0]]}, {"params": [flat.buffers[1]], "lr": 3e-2}],
        fused=True,
        **settings,
    )
    for _ in range(5):
        x = torch.randn(16, 5)
        plain_opt.zero_grad()
        plain(x).square().sum().backward()
        plain_norm = torch.nn.utils.clip_grad_norm_(plain.parameters(), 0.5)
        plain_opt.step()
        flat.zero_grad()
        flat_model(x).square().sum().backward()  # accumulates into the flat gradients
        flat_norm = flat.clip_grad_norm_(0.5)
        flat_opt.step()
        assert plain_norm > 0.5  # the clip is exercised
        assert torch.allclose(plain_norm, flat_norm, rtol=1e-5)
    for a, b in zip(plain.parameters(), flat_model.parameters(), strict=True):
        assert torch.allclose(a, b, atol=1e-6)

    saved = flat.per_parameter_state(flat_opt.state_dict())
    expected = plain_opt.state_dict()
    assert [g["params"] for g in saved["param_groups"]] == [[0, 1], [2, 3]]
    assert saved["state"].keys() == expected["state"].keys()
    for i, state in expected["state"].items():
        assert saved["state"][i].keys() == state.keys()
        for key, value in state.items():
            assert saved["state"][i][key].shape == value.shape, (i, key)
            assert torch.allclose(saved["state"][i][key], value, atol=1e-6), (i, key)

    flat_opt.load_state_dict(flat.flat_state(expected))  # a per-parameter checkpoint loads
    loaded = flat_opt.state_dict()["state"][1]["exp_avg_sq"]
    parts = [expected["state"][i]["exp_avg_sq"].reshape(-1) for i in (2, 3)]
    assert torch.equal(loaded, torch.cat(parts))


def test_only_steps_the_chosen_group_as_if_it_had_an_optimizer_of_its_own():
    """HAPPO's agents: while one group steps, the others' weights, Adam moments and step
    counts stay as they were, and the chosen group moves exactly as a lone Adam moves it."""
    torch.manual_seed(0)
    model = nn.Sequential(nn.Linear(4, 4), nn.Tanh(), nn.Linear(4, 2))
    flat = FlatParameters([list(model[0].parameters()), list(model[2].parameters())])
    optimizer = torch.optim.Adam([{"params": [b]} for b in flat.buffers], lr=1e-2, fused=True)
    x = torch.randn(8, 4)
    flat.zero_grad()
    model(x).sum().backward()
    with flat.only([0]):  # the first group steps once and has moments; the second none
        optimizer.step()
    first = flat.buffers[0].detach().clone()
    moments = {k: v.clone() for k, v in optimizer.state[flat.buffers[0]].items()}
    alone = copy.deepcopy(model[2])
    alone_optimizer = torch.optim.Adam(alone.parameters(), lr=1e-2)
    for _ in range(3):
        flat.zero_grad()
        model(x).sum().backward()
        alone_optimizer.zero_grad()
        alone(torch.tanh(model[0](x)).detach()).sum().backward()
        with flat.only([1]):
            optimizer.step()
        alone_optimizer.step()
        assert flat.buffers[0].grad.abs().sum() > 0  # a gradient it was not stepped by
    assert torch.equal(flat.buffers[0], first)
    for key, value in optimizer.state[flat.buffers[0]].items():
        assert torch.equal(value, moments[key]), key
    for ours, lone in zip(model[2].parameters(), alone.parameters(), strict=True):
        assert torch.allclose(ours, lone, atol=1e-6)
