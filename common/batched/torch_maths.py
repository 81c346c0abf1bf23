"""The numpy engine's policy maths in torch, on any torch device (``algo.engine=torch``).

Made for a CUDA GPU: a host's per-step forward of every copy and the gradients of ended
batches become a few batched products on the device, while the environments, random
streams, coefficients and ascent steps stay in numpy on the CPU. Each step moves the
observations and uniforms to the device and the actions back.

The same formulas as :mod:`fedhpg.common.batched.mlp` (float32; the draw inverts the CDF with
float64 thresholds, like numpy's promotion; an agent's chunks summed in order, without
atomics, so a device gives the same θ run after run). Bit-identity across placements is not
promised: a device library picks its product kernels by shape, so an agent's last bits may
depend on the batch it shares, and its episodes (hence θ) may then diverge. On the CPU
(``algo.device=cpu``) it holds, and the module is tested there against the numpy maths;
``make bench-device`` checks both properties on the device. The numpy engine stays the
default.
"""

from __future__ import annotations

import numpy as np
import torch

from fedhpg.common.batched import mlp

TorchLayers = list[tuple[torch.Tensor, torch.Tensor]]
"""Per layer: weights [A, in, out] and biases [A, 1, out], float32, on the device."""


class TorchMaths:
    """Per-agent MLP maths with torch on ``device`` ('cpu', 'cuda', 'cuda:1', …)."""

    def __init__(self, device: str) -> None:
        self.device = torch.device(device)

    def _put(self, array: np.ndarray) -> torch.Tensor:
        return torch.from_numpy(np.ascontiguousarray(array)).to(self.device, non_blocking=True)

    @torch.no_grad()
    def unflatten(self, shape: mlp.MLPShape, theta: np.ndarray) -> TorchLayers:
        flat = self._put(theta.astype(np.float32, copy=False))
        layers = []
        for offset, n_in, n_out in shape.layers:
            weight = flat[:, offset : offset + n_in * n_out].reshape(-1, n_out, n_in)
            bias = flat[:, offset + n_in * n_out : offset + n_in * n_out + n_out]
            layers.append((weight.transpose(1, 2).contiguous(), bias[:, None, :].clone()))
        return layers

    def _index(self, rows: np.ndarray) -> torch.Tensor:
        return self._put(np.asarray(rows, dtype=np.int64))

    def select(self, layers: TorchLayers, rows: np.ndarray) -> TorchLayers:
        index = self._index(rows)
        return [(w.index_select(0, index), b.index_select(0, index)) for w, b in layers]

    def assign(self, layers: TorchLayers, rows: np.ndarray, fresh: TorchLayers) -> None:
        index = self._index(rows)
        for (weight, bias), (new_w, new_b) in zip(layers, fresh, strict=True):
            weight.index_copy_(0, index, new_w)
            bias.index_copy_(0, index, new_b)

    @staticmethod
    def _forward(layers: TorchLayers, x: torch.Tensor) -> list[torch.Tensor]:
        activations = [x]
        for i, (weight, bias) in enumerate(layers):
            h = torch.baddbmm(bias, activations[-1], weight)
            if i < len(layers) - 1:
                h = torch.tanh(h)
            activations.append(h)
        return activations

    @torch.no_grad()
    def act(self, layers: TorchLayers, obs: np.ndarray, uniforms: np.ndarray | None) -> np.ndarray:
        logit = self._forward(layers, self._put(obs))[-1]
        logit = logit.reshape(-1, logit.shape[-1])
        if uniforms is None:
            return logit.argmax(dim=-1).cpu().numpy()
        cumulative = torch.exp(logit - logit.max(dim=-1, keepdim=True).values).cumsum(dim=-1)
        thresholds = self._put(uniforms.astype(np.float64, copy=False)) * cumulative[:, -1]
        # like mlp.draw_actions: the last action is never exceeded, whatever the rounding
        actions = (thresholds[:, None] > cumulative[:, :-1].double()).sum(dim=-1)
        return actions.cpu().numpy()

    @torch.no_grad()
    def score_gradient(
        self, shape: mlp.MLPShape, layers: TorchLayers, chunks: mlp.Chunks
    ) -> np.ndarray:
        num_chunks = len(chunks.owner)
        owner = self._index(chunks.owner)
        per_chunk = [(w.index_select(0, owner), b.index_select(0, owner)) for w, b in layers]
        activations = self._forward(per_chunk, self._put(chunks.obs))
        logit = activations[-1]
        onehot = torch.nn.functional.one_hot(self._put(chunks.actions), logit.shape[-1])
        delta = (onehot - torch.softmax(logit, dim=-1)) * self._put(chunks.coef)[..., None]
        parts = torch.empty((num_chunks, shape.num_params), dtype=torch.float32, device=self.device)
        for i in reversed(range(len(per_chunk))):
            offset, n_in, n_out = shape.layers[i]
            below = activations[i]
            parts[:, offset : offset + n_in * n_out] = torch.bmm(
                delta.transpose(1, 2), below
            ).reshape(num_chunks, -1)
            parts[:, offset + n_in * n_out : offset + n_in * n_out + n_out] = delta.sum(dim=1)
            if i > 0:
                delta = torch.bmm(delta, per_chunk[i][0].transpose(1, 2)) * (1.0 - below * below)
        # each agent's chunks added in order, as in mlp.score_gradient: no atomics, so a
        # device gives the same sums run after run
        first, count = self._index(chunks.first), chunks.count
        gradient = parts.index_select(0, first)
        for j in range(1, int(count.max())):
            agents = np.nonzero(count > j)[0]
            later = parts.index_select(0, self._index(chunks.first[agents] + j))
            gradient.index_add_(0, self._index(agents), later)
        return gradient.cpu().numpy()
