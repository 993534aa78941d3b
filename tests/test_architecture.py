"""The layering of flipviz/: no import cycles, and imports only run down the layers.

    flipviz (errors, files) -> data -> geometry -> model -> training -> viz -> bench -> cli / app

Every import counts: module level, inside functions, and under TYPE_CHECKING.
"""

from __future__ import annotations

import ast
from pathlib import Path

PKG = Path(__file__).resolve().parents[1] / "flipviz"
LAYERS = ("", "data", "geometry", "model", "training", "viz", "bench", "cli")


def module_name(path: Path) -> str:
    parts = list(path.relative_to(PKG.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def modules() -> dict[str, Path]:
    return {module_name(p): p for p in PKG.rglob("*.py")}


def imports(path: Path, known: set[str]) -> set[str]:
    """The flipviz modules `path` imports (a name imported from a package is its submodule when one exists)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names if a.name.startswith("flipviz")}
        elif isinstance(node, ast.ImportFrom) and node.module and node.module.startswith("flipviz"):
            for a in node.names:
                sub = f"{node.module}.{a.name}"
                out.add(sub if sub in known else node.module)
    return out & known


def graph() -> dict[str, set[str]]:
    mods = modules()
    return {m: imports(p, set(mods)) - {m} for m, p in mods.items()}


def layer(mod: str) -> int:
    parts = mod.split(".")
    if parts[-1] == "__main__" or mod == "flipviz.cli":
        return LAYERS.index("cli")
    name = parts[1] if len(parts) > 2 or (len(parts) == 2 and parts[1] in LAYERS) else ""
    return LAYERS.index(name)


def find_cycle(g: dict[str, set[str]]) -> list[str] | None:
    state: dict[str, int] = {}  # 1 on the stack, 2 done
    stack: list[str] = []

    def visit(m: str) -> list[str] | None:
        state[m] = 1
        stack.append(m)
        for n in sorted(g[m]):
            if state.get(n) == 1:
                return stack[stack.index(n) :] + [n]
            if n not in state and (c := visit(n)):
                return c
        stack.pop()
        state[m] = 2
        return None

    for m in sorted(g):
        if m not in state and (c := visit(m)):
            return c
    return None


def test_the_walker_sees_imports():
    g = graph()
    assert "flipviz.model.objective" in g["flipviz.training.flip"]
    assert "flipviz.training.trainer" in g["flipviz.training"]  # a lazy import inside a function
    assert find_cycle({"a": {"b"}, "b": {"c"}, "c": {"a"}}) == ["a", "b", "c", "a"]
    assert find_cycle({"a": {"b"}, "b": set()}) is None


def test_no_import_cycles():
    assert find_cycle(graph()) is None


def test_imports_only_run_down_the_layers():
    bad = [
        f"{m} ({LAYERS[layer(m)] or 'base'}) imports {n} ({LAYERS[layer(n)] or 'base'})"
        for m, ns in graph().items()
        for n in ns
        if layer(n) > layer(m)
    ]
    assert not bad, "\n".join(bad)


def test_the_trainer_sees_flip_only_through_its_interface():
    """trainer.py is a NeRF loop: what Just Flip adds is reached through `self.flip` (flip.py's hooks), never
    through FlipConfig or Flip's internals (issue 42: 111 lines of Flip-only methods had grown in the Trainer)."""
    src = (PKG / "training/trainer.py").read_text()
    tree = ast.parse(src)
    flip_imports = [n for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module == "flipviz.training.flip"]
    from_flip = {a.name for n in flip_imports for a in n.names}
    assert from_flip == {"Action"}
    assert "cfg.flip" not in src
    inner = ("agreement", "dropped_at", "refiner", "plane", "opt_pose", "opt_plane", "objective", "mirrors")
    reads = {
        n.attr
        for n in ast.walk(tree)
        if isinstance(n, ast.Attribute)
        and isinstance(n.value, ast.Attribute)
        and n.value.attr == "flip"
        and n.attr in inner
    }
    assert not reads, f"the trainer reads Flip's internals: {sorted(reads)}"
    (trainer,) = [n for n in tree.body if isinstance(n, ast.ClassDef) and n.name == "Trainer"]
    lines = trainer.end_lineno - trainer.lineno + 1
    assert lines <= 330, f"Trainer has {lines} lines: what it gained belongs behind an interface (issue 42: <= 330)"


VIZ_WINGS = ("floor", "rerun", "export", "app")  # viz/: the shared floor, then its wings; the app may use them all


def wing(mod: str) -> str:
    """A viz module's wing: viz/rerun/, viz/export/, viz/app/, or the floor (viz/*.py)."""
    parts = mod.split(".")
    return parts[2] if len(parts) > 3 and parts[2] in VIZ_WINGS else "floor"


def third_party(path: Path) -> set[str]:
    """The top-level packages outside flipviz that `path` imports."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out |= {a.name.split(".")[0] for a in node.names}
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module.split(".")[0])
    return out - {"flipviz"}


def test_viz_has_three_wings_over_a_floor_and_only_the_app_imports_viser():
    """The floor (palette, curves, images, splats, run events) imports no wing; Rerun and the exports import
    neither each other's nor the app's modules, nor viser: a video or a report runs without a browser app."""
    mods, g = modules(), graph()
    viz = {m for m in mods if m.startswith("flipviz.viz.")}
    assert {wing(m) for m in viz} == set(VIZ_WINGS), sorted(viz)
    assert not [p.name for p in (PKG / "viz").glob("*.py") if p.name.startswith(("viser_", "rerun_"))]
    wrong = [
        (m, n) for m in viz for n in g[m] if n in viz and wing(n) != wing(m) and wing(n) != "floor" and wing(m) != "app"
    ]
    assert not wrong, wrong
    viser = sorted(m for m in viz if wing(m) != "app" and "viser" in third_party(mods[m]))
    assert not viser, viser
