"""Shared fixtures."""

from __future__ import annotations

import pytest
import torch


@pytest.fixture
def small_torch(tmp_path, monkeypatch):
    """A private render cache, a fixed seed and one torch thread (small model tests)."""
    monkeypatch.setenv("FLIPVIZ_CACHE", str(tmp_path / "cache"))
    torch.manual_seed(0)
    # One thread: on a shared, oversubscribed 2-core machine two OpenMP threads made these small
    # steps ~28x slower (measured before OMP_WAIT_POLICY=PASSIVE: 150 grid steps 4.4 s vs 122 s).
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)
