"""A minibatch's PPO gradient, computed in this process or split with update workers.

On a CPU one update step is bound by one core: its ~65 small matmuls and three tiny
attentions run near the core's peak, and a second torch thread only adds synchronisation
(BENCHMARKS.md). A second core helps through data parallelism instead: with `workers=W`,
every minibatch's rows are split W + 1 ways. Each worker process computes the gradient of
its share on the same weights (its parameters are this process's, in shared memory) while
this process computes its own; this process then sums the gradients, and the trainer clips
them and steps the optimizer. Each share's loss is weighted by its fraction of the rows, so
the sum is the gradient of the whole minibatch's mean loss: the same math as one process,
up to float rounding.
"""

from __future__ import annotations

import multiprocessing as mp
from typing import TYPE_CHECKING

import torch
import torch.multiprocessing  # registers the sharing of tensors sent through a pipe
from torch import Tensor

from mat_sdk.common import processes
from mat_sdk.common.processes import WorkerProcess, close_all, serve, wait_all
from mat_sdk.policy.model import PolicyNetwork
from mat_sdk.training.flat_params import FlatParameters, views
from mat_sdk.training.ppo import LossCoefficients, LossTerms, Rows, minibatch_loss

if TYPE_CHECKING:
    from mat_sdk.policy.config import TrainConfig

_TERMS = ("total", "policy", "value", "entropy", "clip_fraction", "kl")  # LossTerms' fields


def _bounds(rows: int, parts: int) -> list[int]:
    """Where each of `parts` shares of `rows` starts, then the end. The first share, this
    process's, is never the larger: it also sums the gradients."""
    return [rows * k // parts for k in range(parts + 1)]


def _loss_function(compile_mode: str | None):
    if compile_mode is None:
        return minibatch_loss
    # Static shapes: within a run every minibatch share has the same rows. (A second shape
    # in one process, as in `mat bench train`, gets its own graph instead of dynamic ones.)
    return torch.compile(minibatch_loss, mode=compile_mode, dynamic=False)


def _share_backward(
    loss, policy, coefficients, batch, rows: Tensor, targets: Tensor, weight: float
):
    """Backpropagate the loss of one share of a minibatch, weighted by its fraction of the
    rows; its weighted loss terms, stacked as `_TERMS`."""
    terms = loss(policy, batch[rows], targets, coefficients)
    (terms.total * weight).backward()
    return torch.stack([getattr(terms, name).detach() for name in _TERMS]) * weight


class _Share:
    """A worker's side: on each step, the gradient of its share of the current minibatch,
    accumulated straight into shared buffers laid out like the caller's flat gradients."""

    def __init__(
        self, policy: PolicyNetwork, config: TrainConfig, compile_mode, rank, parts, shared
    ):
        config.run.configure_torch()
        self.policy, self.rank, self.parts = policy, rank, parts
        self.coefficients = LossCoefficients.of(config.ppo)
        self.loss = _loss_function(compile_mode)
        self.rows, layout, self.grads, self.terms = shared
        params = list(policy.parameters())
        for indices, grad in zip(layout, self.grads, strict=True):
            group = [params[i] for i in indices]
            for param, view in zip(group, views(grad, group), strict=True):
                param.grad = view
        self.update_batch = self.idx = self.targets = None

    def batch(self, batch: dict[str, Tensor], idx: Tensor, targets: Tensor) -> None:
        """This update's rows; each step's minibatch indexes into them."""
        self.update_batch, self.idx, self.targets = batch, idx, targets

    def step(self) -> None:
        rows = int(self.rows[0])
        lo, hi = _bounds(rows, self.parts)[self.rank : self.rank + 2]
        for grad in self.grads:
            grad.zero_()
        terms = _share_backward(
            self.loss,
            self.policy,
            self.coefficients,
            self.update_batch,
            self.idx[lo:hi],
            self.targets[lo:hi],
            (hi - lo) / rows,
        )
        self.terms.copy_(terms)


def _worker(conn, handshake, policy, config, compile_mode, rank, parts, shared):
    serve(conn, handshake, lambda: _Share(policy, config, compile_mode, rank, parts, shared))


class MinibatchGradients:
    """Adds each minibatch's loss gradient to the policy's flat gradients (`params`),
    computed by this process alone (`workers=0`) or split with `workers` update worker
    processes (CPU).

        gradients.share(batch)                   # once per update: the batch as rows
        terms = gradients.backward(idx, targets)  # per minibatch: its row indices, targets

    The workers start on the first `share` (or `start`), and read the policy's weights
    from shared memory: the caller may change them in place between minibatches.
    """

    def __init__(
        self,
        policy: PolicyNetwork,
        params: FlatParameters,
        config: TrainConfig,
        workers: int = 0,
        compile_mode: str | None = None,
    ):
        self.policy, self.params, self.config, self.workers = policy, params, config, workers
        self.coefficients = LossCoefficients.of(config.ppo)
        self.compile_mode = compile_mode
        self._loss = _loss_function(compile_mode)
        self._batch: dict[str, Tensor] = {}
        self._workers: list[WorkerProcess] = []
        self._setting_up = self._closed = False

    def start(self) -> None:
        """Start the update workers now (they take a few seconds to import torch)."""
        if self._closed:
            raise RuntimeError("the update workers are closed")
        if self._workers or not self.workers:
            return
        self.policy.share_memory()  # the flat parameter buffers, which the parameters view
        index = {id(p): i for i, p in enumerate(self.policy.parameters())}
        layout = [[index[id(p)] for p in group] for group in self.params.groups]
        self._rows = torch.zeros(1, dtype=torch.int64).share_memory_()
        self._idx = self._targets = torch.empty(0)
        self._results = []
        context = mp.get_context("spawn")
        spin = processes.SPIN_SECONDS if self.workers < processes.usable_cores() else 0.0
        parts = self.workers + 1
        for rank in range(1, parts):
            grads = [torch.zeros_like(b).share_memory_() for b in self.params.buffers]
            terms = torch.zeros(len(_TERMS)).share_memory_()
            self._results.append((grads, terms))
            shared = (self._rows, layout, grads, terms)
            arguments = (self.policy, self.config, self.compile_mode, rank, parts, shared)
            self._workers.append(WorkerProcess(context, _worker, arguments, spin))
        self._setting_up = True

    def share(self, batch: Rows) -> None:
        """This update's rows; minibatches index into them."""
        self._batch = batch
        if not self.workers:
            return
        self.start()
        if self._setting_up:
            self._wait()
            self._setting_up = False
        rows = len(batch)
        if self._idx.shape[0] < rows:
            self._idx = torch.empty(rows, dtype=torch.int64).share_memory_()
            self._targets = torch.empty_like(batch.returns).share_memory_()
        for value in batch.tensors().values():
            value.share_memory_()
        for worker in self._workers:
            worker.go("batch", (batch, self._idx, self._targets))
        self._wait()

    def backward(self, idx: Tensor, targets: Tensor) -> LossTerms:
        """Accumulate into `.grad` the gradient of the mean loss over rows `idx` (targets:
        their normalised returns); returns the minibatch's loss terms."""
        if not self.workers:
            terms = self._loss(self.policy, self._batch[idx], targets, self.coefficients)
            terms.total.backward()
            return terms
        rows = idx.shape[0]
        if rows < self.workers + 1:
            raise ValueError(f"a minibatch of {rows} rows cannot be split {self.workers + 1} ways")
        self._idx[:rows] = idx
        self._targets[:rows] = targets
        self._rows[0] = rows
        for worker in self._workers:
            worker.go()
        own = _bounds(rows, self.workers + 1)[1]
        try:
            terms = _share_backward(
                self._loss,
                self.policy,
                self.coefficients,
                self._batch,
                idx[:own],
                targets[:own],
                own / rows,
            )
        finally:  # the workers' round ends either way
            self._wait()
        for worker_grads, worker_terms in self._results:
            for buffer, grad in zip(self.params.buffers, worker_grads, strict=True):
                buffer.grad.add_(grad)
            terms += worker_terms
        return LossTerms(*terms)

    def close(self) -> None:
        if not self._closed:
            self._closed = True
            close_all(self._workers)

    def _wait(self) -> None:
        wait_all(self._workers, "update worker failed", self.close)
