"""The engine's host views of tensors it reads again and again: always what the tensor holds."""

from __future__ import annotations

import torch

from fedhpg.common.learning.engine.host_arrays import KEPT, HostArrays


def test_a_view_follows_the_tensor_stepped_in_place() -> None:
    host = HostArrays()
    theta = torch.zeros((2, 3))
    view = host(theta)
    theta += 1.5  # a loop's step: the same tensor, new values
    again = host(theta)
    assert again is view
    assert again.tolist() == [[1.5] * 3] * 2


def test_another_tensor_gets_its_own_view() -> None:
    host = HostArrays()
    first, second = torch.tensor([1, 2]), torch.tensor([1, 2])
    assert host(first) is not host(second)
    second[0] = 7
    assert host(first).tolist() == [1, 2]
    assert host(second).tolist() == [7, 2]


def test_it_holds_a_bounded_number_of_tensors() -> None:
    host = HostArrays()
    tensors = [torch.tensor([i]) for i in range(3 * KEPT)]
    for i, tensor in enumerate(tensors):
        assert host(tensor).tolist() == [i]
    assert len(host._kept) <= KEPT
