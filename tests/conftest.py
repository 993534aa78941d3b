"""Shared fixtures."""

from __future__ import annotations

import os
from pathlib import Path

import pytest
import torch


@pytest.fixture(scope="session", autouse=True)
def render_cache(tmp_path_factory) -> Path:
    """One render cache for the whole session, never the user's (~/.cache/flipviz): the built-in scenes
    render once per session, and the subprocesses a test starts inherit it. A test of the cache itself
    sets its own with monkeypatch."""
    cache = tmp_path_factory.getbasetemp() / "cache"
    with pytest.MonkeyPatch.context() as m:
        m.setenv("FLIPVIZ_CACHE", str(cache))
        yield cache


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


def find_lego() -> Path | None:
    """The NeRF-synthetic lego test orbit: $FLIPVIZ_LEGO, or ../shared beside the checkout."""
    env = os.environ.get("FLIPVIZ_LEGO")
    p = Path(env) if env else Path(__file__).resolve().parents[2] / "shared" / "data" / "nerf_synthetic" / "lego"
    return p if (p / "transforms_test.json").is_file() else None


@pytest.fixture
def lego_dir() -> Path:
    """The lego folder; the test is skipped cleanly when it is absent (a user's fresh clone)."""
    p = find_lego()
    if p is None:
        pytest.skip("NeRF-synthetic lego not found (set FLIPVIZ_LEGO)")
    return p
