"""Fuzz the readers of files a user is handed: a dataset folder (Blender, nerfstudio) and a run's
checkpoint. Each is mutated by a seeded loop, and every mutation must load or fail in one line (a
`UserError`), never with a traceback (docs/RELIABILITY.md, "Bad input").

The loop is seeded, so a failure names its seed and repeats; its size bounds the time (about a
minute on the 2-core machine).
"""

from __future__ import annotations

import json
import os
import random
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest
import torch

from flipviz.data import export_scene, load_scene
from flipviz.data.driveby import export_driveby
from flipviz.errors import UserError
from flipviz.training.checkpoint import load_checkpoint
from flipviz.training.config import TrainConfig
from flipviz.training.saved_run import open_run
from flipviz.training.setup import run_split
from flipviz.training.trainer import Trainer

TINY = dict(
    scene="chair", res=24, batch_rays=256, n_samples=32, grid_res=(24,), images_every=0, mirror_plane="official"
)
N_JSON, N_BYTES, N_STATE = 60, 30, 40  # mutations per file kind
SEED = int(os.environ.get("FLIPVIZ_FUZZ_SEED", "0"))  # another seed explores further: FLIPVIZ_FUZZ_SEED=7 pytest ...

# What a mutation puts in a JSON value's place: wrong types, out-of-range numbers, NaN and Infinity
# (written as Python's json writes them), deep nesting, paths that leave the folder.
ODD_VALUES = [
    None,
    True,
    0,
    -1,
    10**30,
    1e300,
    float("inf"),
    float("nan"),
    -0.0,
    "",
    "x",
    "../../../../etc/passwd",
    "/etc/passwd",
    "a\x00b",
    [],
    {},
    [[[[[]]]]],
    [1, 2],
    [[1, 0, 0], [0, 1, 0]],
    {"a": 1},
    "A" * 5000,
]


def _nodes(obj, depth: int = 0):
    """Every (depth, container, key) inside a parsed JSON value."""
    items = obj.items() if isinstance(obj, dict) else enumerate(obj) if isinstance(obj, list) else ()
    for k, v in items:
        yield depth, obj, k
        yield from _nodes(v, depth + 1)


def mutate_json(doc, rng: random.Random):
    """1-3 structural edits: a value replaced by an odd one, a key deleted, an item duplicated. The
    depth is drawn first, so the few top-level fields are hit as often as the many matrix entries."""
    doc = json.loads(json.dumps(doc))
    for _ in range(rng.randint(1, 3)):
        nodes = list(_nodes(doc))
        if not nodes:
            return rng.choice(ODD_VALUES)
        depth = rng.choice(sorted({d for d, _, _ in nodes}))
        _, parent, key = rng.choice([n for n in nodes if n[0] == depth])
        edit = rng.random()
        if edit < 0.6:
            parent[key] = rng.choice(ODD_VALUES)
        elif edit < 0.8:
            del parent[key]
        elif isinstance(parent, list):
            parent.insert(key, parent[key])
        else:
            parent[key + "_"] = parent[key]
    return doc


def mutate_bytes(data: bytes, rng: random.Random) -> bytes:
    """Truncated, or a few bytes overwritten."""
    if rng.random() < 0.4:
        return data[: rng.randrange(len(data))]
    out = bytearray(data)
    for _ in range(rng.randint(1, 8)):
        out[rng.randrange(len(out))] = rng.randrange(256)
    return bytes(out)


def loads_or_one_line(load: Callable[[], object], what: str) -> bool:
    """True if the reader succeeds, False if it raises a UserError of one line; anything else fails
    the test with `what`."""
    try:
        load()
        return True
    except UserError as e:
        assert str(e) and "\n" not in str(e), f"{what}: a UserError of several lines: {e!r}"
        return False
    except Exception as e:
        raise AssertionError(f"{what}: {type(e).__name__}: {str(e)[:300]}") from e


def _read_folder(root: Path) -> None:
    """What a run does with a data folder before it trains: load it and pick its views."""
    run_split(TrainConfig.from_settings(data=root, res=16), load_scene("", root, res=16))


@pytest.mark.filterwarnings("error::RuntimeWarning")  # an overflow or NaN let through is a failure too
@pytest.mark.parametrize("fmt", ["blender", "nerfstudio"])
def test_mutated_dataset_folders_load_or_fail_in_one_line(tmp_path, fmt):
    good = tmp_path / "good"
    if fmt == "blender":
        export_scene("chair", good, res=16)
        jname = "transforms_test.json"
    else:
        export_driveby("chair", good, res=16)
        jname = "transforms.json"
    doc = json.loads((good / jname).read_text())
    images = sorted(p for p in good.rglob("*.png"))
    rng = random.Random(SEED)
    loaded = []
    for i in range(N_JSON + N_BYTES):
        case = tmp_path / f"case{i}"
        shutil.copytree(good, case)
        if i < N_JSON:  # the JSON, edited as data
            what = mutate_json(doc, rng)
            (case / jname).write_text(json.dumps(what))
        elif i % 2:  # the JSON's bytes
            (case / jname).write_bytes(mutate_bytes((good / jname).read_bytes(), rng))
        else:  # an image's bytes
            img = case / rng.choice(images).relative_to(good)
            img.write_bytes(mutate_bytes(img.read_bytes(), rng))
        loaded.append(loads_or_one_line(lambda: _read_folder(case), f"{fmt} mutation {i}"))
        shutil.rmtree(case)
    assert 1 <= sum(loaded) <= len(loaded) - 1  # the mutations reach both outcomes: the loop tests something


@pytest.fixture(scope="module")
def run_folder(tmp_path_factory) -> Path:
    out = tmp_path_factory.mktemp("fuzz_run") / "run"
    Trainer(TrainConfig.from_settings(**TINY, steps=3, method="flip+u", out=out)).run()
    return out


def _mutate_state(state: dict, rng: random.Random) -> dict:
    """A checkpoint's state with one entry (at any depth) removed or replaced by an odd value or tensor."""
    state = {k: v for k, v in state.items()}
    nodes = [(state, k) for k in state]
    for k, v in state.items():
        if isinstance(v, dict):
            state[k] = v = dict(v)
            nodes += [(v, kk) for kk in v]
    parent, key = rng.choice(nodes)
    odd = ODD_VALUES + [
        torch.zeros(3),
        torch.full((2, 2), float("nan")),
        torch.zeros(0),
        torch.ones(5, dtype=torch.int64),
    ]
    if rng.random() < 0.25:
        del parent[key]
    else:
        parent[key] = rng.choice(odd)
    return state


@pytest.mark.filterwarnings("error::RuntimeWarning")
@pytest.mark.slow
def test_mutated_checkpoints_open_resume_or_fail_in_one_line(run_folder, tmp_path):
    ckpt = run_folder / "checkpoint.pt"
    state = torch.load(ckpt, weights_only=True)
    rng = random.Random(SEED)
    resumed = []
    for i in range(N_BYTES + N_STATE):
        case = tmp_path / f"case{i}"
        case.mkdir()
        if i < N_BYTES:
            (case / "checkpoint.pt").write_bytes(mutate_bytes(ckpt.read_bytes(), rng))
            loads_or_one_line(lambda: load_checkpoint(case), f"checkpoint bytes mutation {i}")
        else:
            torch.save(_mutate_state(state, rng), case / "checkpoint.pt")
        loads_or_one_line(lambda: open_run(case), f"checkpoint mutation {i}: open")  # report, video, Compare's B
        cfg = TrainConfig.from_settings(
            **TINY, steps=5, method="flip+u", out=tmp_path / f"resumed{i}", resume=case / "checkpoint.pt"
        )
        resumed.append(loads_or_one_line(lambda: Trainer(cfg), f"checkpoint mutation {i}: resume"))
        shutil.rmtree(case)
    assert 1 <= sum(resumed) <= len(resumed) - 1
