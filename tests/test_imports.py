"""The data flows one way (docs/architecture.md): a module imports only from the layers before
it. Read from the source (every import statement, including those inside functions), so an
arrow against the flow fails here whether or not it runs."""

import ast
from pathlib import Path

import stepnft

PACKAGE = Path(stepnft.__file__).parent
LOW = ("envs", "data", "policies", "rollout")
HIGH = ("algos", "train", "compare", "cli")


def part(module: str) -> str:
    """The folder (or top-level module) a dotted ``stepnft.x.y`` module belongs to."""
    return module.split(".")[1] if module.count(".") >= 1 else module


def imports() -> dict[str, set[str]]:
    """``{importing part: {imported parts}}`` over every module of the package."""
    graph: dict[str, set[str]] = {}
    for path in PACKAGE.rglob("*.py"):
        name = ".".join(("stepnft", *path.relative_to(PACKAGE).with_suffix("").parts))
        package = name if path.name == "__init__.py" else name.rsplit(".", 1)[0]
        for node in ast.walk(ast.parse(path.read_text())):
            targets = []
            if isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    base = ".".join(package.split(".")[: len(package.split(".")) - node.level + 1] + [base]).strip(".")
                targets = [base]
            for target in targets:
                if target.startswith("stepnft.") and part(target) != part(name):
                    graph.setdefault(part(name), set()).add(part(target))
    return graph


def test_the_lower_layers_import_nothing_above_them():
    graph = imports()
    wrong = {low: sorted(graph.get(low, set()) & set(HIGH)) for low in LOW}
    assert not any(wrong.values()), wrong


def test_no_cycle_between_folders_and_modules():
    graph = imports()

    def reaches(start: str, goal: str, seen: set[str]) -> bool:
        for nxt in graph.get(start, ()):
            if nxt == goal or (nxt not in seen and reaches(nxt, goal, seen | {nxt})):
                return True
        return False

    cycles = sorted(p for p in graph if reaches(p, p, {p}))
    assert not cycles, {p: sorted(graph[p]) for p in cycles}
