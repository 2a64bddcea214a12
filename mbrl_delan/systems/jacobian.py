"""Central differences of a batched function of configurations, for numpy or torch."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from typing import TypeVar

import numpy as np
import torch

Array = TypeVar("Array", np.ndarray, torch.Tensor)


def central_jacobian(
    f: Callable[[Array], Array], q: Array, coordinates: Sequence[int], step: float
) -> Array:
    """d f / d q_c for each of `coordinates` at configurations q (N, nq), by central
    differences of `step`: f's outputs (N, m) stacked along a last axis. (N, m, C)"""
    columns = []
    for c in coordinates:
        delta = q * 0  # zeros of q's kind, dtype and device
        delta[:, c] = step
        columns.append((f(q + delta) - f(q - delta)) / (2 * step))
    if isinstance(q, torch.Tensor):
        return torch.stack(columns, -1)
    return np.stack(columns, -1)
