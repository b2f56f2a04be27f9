"""A policy's parameters laid out in one buffer per optimizer group, gradients likewise.

MAT has ~65 small parameter tensors. Torch's clip and Adam launch kernels for each of them,
a real share of a CPU update step, and all of it on the critical path when the gradient is
split over processes (`mat_sdk.training.gradients`). With every parameter a view into
one flat buffer per group, and every `.grad` a view into a flat gradient buffer that
autograd accumulates into in place, zeroing, clipping and the optimizer step each run one
kernel per group (BENCHMARKS.md). The modules still see ordinary
parameters, so state dicts, export and `torch.compile` are unchanged.

Checkpoints keep the optimizer state per parameter (torch's layout for the unflattened
policy): `per_parameter_state` and `flat_state` convert.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import torch
from torch import Tensor, nn


def views(flat: Tensor, params: list[Tensor]) -> list[Tensor]:
    """`flat` cut into one view per parameter, shaped like it."""
    sizes = [p.numel() for p in params]
    return [v.view_as(p) for v, p in zip(flat.split(sizes), params, strict=True)]


class FlatParameters:
    """Moves each group of parameters into one buffer: `buffers[g]` is a leaf tensor whose
    `.grad` holds the group's gradients. Optimise `buffers`, not the parameters."""

    def __init__(self, groups: list[list[nn.Parameter]]):
        self.groups = groups
        self.buffers: list[Tensor] = []
        for params in groups:
            flat = torch.cat([p.detach().reshape(-1) for p in params])
            flat.grad = torch.zeros_like(flat)
            for param, value, grad in zip(
                params, views(flat, params), views(flat.grad, params), strict=True
            ):
                param.data = value
                param.grad = grad
            self.buffers.append(flat)

    def zero_grad(self) -> None:
        """Zero the gradients in place: autograd then accumulates into the flat buffers."""
        for flat in self.buffers:
            flat.grad.zero_()

    def clip_grad_norm_(self, max_norm: float, groups: list[int] | None = None) -> Tensor:
        """`torch.nn.utils.clip_grad_norm_` over every group (or those in `groups`): the
        total norm before clipping."""
        chosen = [self.buffers[g] for g in groups] if groups is not None else self.buffers
        norms = torch.stack([torch.linalg.vector_norm(flat.grad) for flat in chosen])
        total = torch.linalg.vector_norm(norms)
        scale = torch.clamp(max_norm / (total + 1e-6), max=1.0)
        for flat in chosen:
            flat.grad.mul_(scale)
        return total

    @contextlib.contextmanager
    def only(self, groups: list[int]) -> Iterator[None]:
        """Within: the optimizer sees the gradients of `groups` alone. Torch's Adam skips a
        buffer without a gradient, leaving its moments and step count as they were, so each
        group steps as if it had an optimizer of its own (HAPPO's agents)."""
        hidden = {g: flat.grad for g, flat in enumerate(self.buffers) if g not in groups}
        for g in hidden:
            self.buffers[g].grad = None
        try:
            yield
        finally:
            for g, grad in hidden.items():
                self.buffers[g].grad = grad

    def per_parameter_state(self, flat_state: dict[str, Any]) -> dict[str, Any]:
        """An optimizer state dict over `buffers` as one over the parameters, group by group."""
        state: dict[int, dict] = {}
        param_groups = []
        index = 0
        for g, (group, params) in enumerate(
            zip(flat_state["param_groups"], self.groups, strict=True)
        ):
            buffer_state = flat_state["state"].get(g)
            ids = list(range(index, index + len(params)))
            if buffer_state is not None:
                per_param = {  # a scalar (Adam's step) is every parameter's
                    key: [value] * len(params) if value.dim() == 0 else views(value, params)
                    for key, value in buffer_state.items()
                }
                for k, i in enumerate(ids):
                    state[i] = {key: values[k].clone() for key, values in per_param.items()}
            param_groups.append({**group, "params": ids})
            index += len(params)
        return {"state": state, "param_groups": param_groups}

    def flat_state(self, per_parameter: dict[str, Any]) -> dict[str, Any]:
        """The inverse of `per_parameter_state`, for `optimizer.load_state_dict`."""
        state: dict[int, dict] = {}
        groups = per_parameter["param_groups"]
        if len(groups) != len(self.groups) or any(
            len(group["params"]) != len(params)
            for group, params in zip(groups, self.groups, strict=True)
        ):
            raise ValueError("the optimizer state does not match this policy's parameters")
        for g, group in enumerate(groups):
            states = [per_parameter["state"].get(i) for i in group["params"]]
            if all(s is not None for s in states):
                state[g] = {
                    key: value
                    if value.dim() == 0
                    else torch.cat([s[key].reshape(-1) for s in states])
                    for key, value in states[0].items()
                }
        param_groups = [{**group, "params": [g]} for g, group in enumerate(groups)]
        return {"state": state, "param_groups": param_groups}


def flat_adam(
    model: nn.Module,
    lr: float,
    eps: float,
    second: nn.Module | None = None,
    second_lr: float | None = None,
    parts: list[nn.Module] | None = None,
) -> tuple[FlatParameters, torch.optim.Adam]:
    """Fused Adam over `model`'s parameters laid out flat: one group, or two when a `second`
    part of the model (e.g. MAPPO's critic) has its own learning rate `second_lr`, or with
    `parts` (HAPPO's actors), one group per part before the rest."""
    groups = [{"params": list(model.parameters())}]
    if second is not None:
        own = {id(p) for p in second.parameters()}
        groups = [
            {"params": [p for p in model.parameters() if id(p) not in own]},
            {"params": list(second.parameters()), "lr": second_lr},
        ]
    if parts:
        placed = {id(p) for part in parts for p in part.parameters()}
        rest = [{**group, "params": [p for p in group["params"] if id(p) not in placed]}
                for group in groups]  # fmt: skip
        groups = [{"params": list(part.parameters())} for part in parts]
        groups += [group for group in rest if group["params"]]
    params = FlatParameters([group.pop("params") for group in groups])
    optimizer = torch.optim.Adam(
        [
            {"params": [buffer], **group}
            for buffer, group in zip(params.buffers, groups, strict=True)
        ],
        lr=lr,
        eps=eps,
        fused=True,
    )
    return params, optimizer
