"""The mutations of studies/check_mutations.py still apply to the current source."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def test_every_mutation_edits_exactly_one_place():
    spec = importlib.util.spec_from_file_location("check_mutations", ROOT / "studies" / "check_mutations.py")
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up
    spec.loader.exec_module(mod)
    assert mod.MUTATIONS and len({m.name for m in mod.MUTATIONS}) == len(mod.MUTATIONS)  # each named once
    for m in mod.MUTATIONS:
        assert (ROOT / m.path).read_text().count(m.old) == 1, m.name
        for t in m.tests:  # the tests that pin it exist (a test renamed would leave the mutant unchecked)
            path, _, name = t.partition("::")
            assert (ROOT / path).is_file() and (not name or f"def {name}(" in (ROOT / path).read_text()), (m.name, t)
