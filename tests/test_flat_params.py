"""Flat parameters: the same steps as torch's clip and Adam, and torch's checkpoint layout."""

import copy

import torch
from torch import nn

from mat_sdk.flat_params import FlatParameters


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
