"""Break the core on purpose, thirteen ways, and check that the test suite notices each one.

    python studies/check_mutations.py             # every mutation, against the tests that pin it
    python studies/check_mutations.py --tests tests   # against the whole suite (slower)

Each mutation is one textual edit of one file, applied in a temporary copy of the repository;
the tests run there (PYTHONPATH puts the copy first). A mutation the tests do not catch is
reported as SURVIVED and the script exits 1. `tests/test_mutations.py` checks that every edit
still applies to the current source.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

import tyro

ROOT = Path(__file__).resolve().parents[1]


@dataclass(frozen=True)
class Mutation:
    name: str
    path: str  # relative to the repository
    old: str  # must occur exactly once in the file
    new: str
    tests: tuple[str, ...] = ("tests/test_objective.py",)  # the tests that pin it


MUTATIONS = (
    Mutation(
        "(a) the NLL is never applied (always MSE)",
        "flipviz/model/objective.py",
        "if step < self.nll_start or not (bool(uncertain.any()) or everywhere):",
        "if True:",
    ),
    Mutation(
        "(b) the MSE warm-up is removed",
        "flipviz/training/flip.py",
        "nll_start = start + int(cfg.uncertainty_start * (steps - start))",
        "nll_start = start",
    ),
    Mutation(
        "(c) the 2 beta_min^2 / 3 rescale is dropped",
        "flipviz/model/objective.py",
        "return (2.0 * b2min * k / 3.0) * torch.where(",
        "return torch.where(",
    ),
    Mutation(
        "(d) the density weight is forced to 0",
        "flipviz/training/flip.py",
        "Objective(beta_min, cfg.density_weight,",
        "Objective(beta_min, 0.0,",
    ),
    Mutation(
        "(e) beta^2 is detached in the renderer",
        "flipviz/model/renderer.py",
        "wp * F.softplus(raw))",
        "wp * F.softplus(raw).detach())",
    ),
    Mutation(
        "(f) BARF's coarse-to-fine window pinned open",
        "flipviz/model/nerf_field.py",
        "self.progress.fill_(step / max(total_steps, 1))",
        "self.progress.fill_(1.0)",
        ("tests/test_model.py",),
    ),
    Mutation(
        "(g) the training-batch PSNR over the channels' sum",
        "flipviz/training/trainer.py",
        '"psnr": psnr(float(((out["rgb"].detach() - target) ** 2).mean())),',
        '"psnr": psnr(float(((out["rgb"].detach() - target) ** 2).sum(-1).mean())),',
        ("tests/test_training.py::test_the_training_batch_psnr_averages_the_squared_error_over_rays_and_channels",),
    ),
    Mutation(
        "(h) the reflect and lookat pose rules swapped",
        "flipviz/geometry/mirror.py",
        'if pose == "reflect":',
        'if pose == "lookat":',
        ("tests/test_geometry.py",),
    ),
    Mutation(
        "(i) the mirrored rays drawn before the mirrors join",
        "flipviz/training/flip.py",
        "inputs_only = self.dropped_at is not None or step - self.rewound < self.start",
        "inputs_only = self.dropped_at is not None",
        ("tests/test_plane_refine.py::test_auto_estimates_the_plane_from_the_runs_own_field_then_the_mirrors_join",),
    ),
    Mutation(
        "(j) a per-mirror verdict drops every kept mirror once one disagrees",
        "flipviz/training/flip.py",
        "return [i for i in kept if ratios[i] > self.mirror_limit]",
        "return kept if any(ratios[i] > self.mirror_limit for i in kept) else []",
        ("tests/test_agreement.py::test_a_mirror_over_the_limit_leaves_alone_and_the_others_train_on",),
    ),
    Mutation(
        "(k) a dropped mirror's rays stay in the sampler",
        "flipviz/training/flip.py",
        "kept += [m for m, at in zip(self.ts.mirror_ids, self.mirror_dropped_at) if at is None]",
        "kept += list(self.ts.mirror_ids)",
        ("tests/test_agreement.py::test_a_mirror_over_the_limit_leaves_alone_and_the_others_train_on",),
    ),
    Mutation(
        "(l) a dropped mirror's pose goes on moving",
        "flipviz/training/flip.py",
        "return c2w.index_copy(0, self.mirror_ids[gone], self.frozen[gone])",
        "return c2w",
        ("tests/test_agreement.py::test_a_mirror_over_the_limit_leaves_alone_and_the_others_train_on",),
    ),
    Mutation(
        "(m) a resumed run forgets which mirrors were dropped",
        "flipviz/training/flip.py",
        "            self.mirror_dropped_at = list(each)\n",
        "            pass\n",
        ("tests/test_agreement.py::test_a_mirror_over_the_limit_leaves_alone_and_the_others_train_on",),
    ),
    Mutation(
        "(n) once every mirror has left, BA's and the plane's backward pass still runs on every batch",
        "flipviz/training/flip.py",
        "        if self.dropped_at is not None:\n            if self._still is None:",
        "        if False:\n            if self._still is None:",
        ("tests/test_agreement.py::test_a_rollback_of_every_mirror_trains_the_inputs_from_the_join_and_resumes",),
    ),
)


def apply(root: Path, m: Mutation) -> None:
    p = root / m.path
    text = p.read_text()
    if text.count(m.old) != 1:
        raise SystemExit(f"mutation {m.name!r}: {m.old!r} occurs {text.count(m.old)} times in {m.path}")
    p.write_text(text.replace(m.old, m.new))


@dataclass
class Args:
    tests: tuple[str, ...] = ()
    """Test paths to run against every mutant (default: each mutation's own tests)."""


def main(args: Args) -> int:
    survived = []
    for m in MUTATIONS:
        with tempfile.TemporaryDirectory(prefix="flipviz-mutant-") as tmp:
            root = Path(tmp)
            for d in ("flipviz", "tests"):
                shutil.copytree(ROOT / d, root / d, ignore=shutil.ignore_patterns("__pycache__"))
            apply(root, m)
            env = dict(os.environ, PYTHONPATH=str(root))
            r = subprocess.run(
                [sys.executable, "-m", "pytest", "-q", "-x", "-p", "no:cacheprovider", *(args.tests or m.tests)],
                cwd=root,
                env=env,
                capture_output=True,
                text=True,
            )
            caught = r.returncode == 1
            last = (r.stdout.strip().splitlines() or ["(no output)"])[-1]
            print(f"{'caught  ' if caught else 'SURVIVED'} {m.name}: {last}", flush=True)
            if not caught:
                survived.append(m.name)
    return 1 if survived else 0


if __name__ == "__main__":
    sys.exit(main(tyro.cli(Args)))
