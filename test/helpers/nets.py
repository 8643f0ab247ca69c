"""Test helper: move a network's BatchNorm layers away from their initial state."""
from __future__ import annotations

import torch


def perturb_batchnorm(net: torch.nn.Module, prefixes: tuple[str, ...] = ('',)) -> None:
    """Random scale and running statistics for every BatchNorm2d whose module name starts with
    one of ``prefixes`` (default: all), so that BN folding and zero-initialised scales are
    really exercised."""
    for name, m in net.named_modules():
        if name.startswith(prefixes) and isinstance(m, torch.nn.BatchNorm2d):
            m.running_mean.uniform_(-0.5, 0.5)
            m.running_var.uniform_(0.5, 2.0)
            m.weight.data.uniform_(0.5, 1.5)
