"""Structure figures of ``src/scanpipe``: import circles, and where ideas are declared.

``python -m benchmarks.structure [--json]`` prints:

- the import circles among scanpipe's modules (strongly connected components of the graph of
  ``import scanpipe…`` / ``from scanpipe… import`` statements, wherever they stand);
- the modules that declare the ``points`` columns (a literal ``"origin_x"`` column name in a
  dict or schema outside the schema module counts as a declaration);
- the names of the motor step across code, CLI options and docs (``--motor-step`` and
  ``motor_step_deg`` are one name in two dresses; hidden deprecated CLI aliases are not
  counted).

The test suite asserts the first (no circles); the others are for the closing notes.
"""

from __future__ import annotations

import argparse
import ast
import json
import re
import sys
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[1]
SRC = ROOT / "src"
#: Every spelling the motor step has had; the figure counts those still in use.
MOTOR_STEP_SPELLINGS = ("step_angle_deg", "motor_step_deg", "--step-angle", "--motor-step",
                        "--angle")


def module_name(path: Path) -> str:
    """``src/scanpipe/a/b.py`` → ``scanpipe.a.b`` (packages by their ``__init__``)."""
    parts = list(path.relative_to(SRC).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def import_graph(src: Path = SRC) -> dict[str, set[str]]:
    """Module → the scanpipe modules it imports (anywhere in the file)."""
    modules = {module_name(p): p for p in src.rglob("*.py")}
    graph: dict[str, set[str]] = {m: set() for m in modules}
    for name, path in modules.items():
        package = name if path.name == "__init__.py" else name.rpartition(".")[0]
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            targets: list[str] = []
            if isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:
                    anchor = package.split(".")
                    anchor = anchor[: len(anchor) - node.level + 1]
                    base = ".".join([*anchor, base] if base else anchor)
                targets = [f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                           for a in node.names]
            elif isinstance(node, ast.Import):
                targets = [a.name for a in node.names]
            graph[name] |= {t for t in targets if t in modules and t != name}
    return graph


def import_circles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan, iterative)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    circles: list[list[str]] = []
    counter = 0
    for root in sorted(graph):
        if root in index:
            continue
        work: list[tuple[str, list[str]]] = [(root, sorted(graph[root]))]
        index[root] = low[root] = counter
        counter += 1
        stack.append(root)
        on_stack.add(root)
        while work:
            node, children = work[-1]
            if children:
                child = children.pop()
                if child not in index:
                    index[child] = low[child] = counter
                    counter += 1
                    stack.append(child)
                    on_stack.add(child)
                    work.append((child, sorted(graph[child])))
                elif child in on_stack:
                    low[node] = min(low[node], index[child])
                continue
            work.pop()
            if work:
                low[work[-1][0]] = min(low[work[-1][0]], low[node])
            if low[node] == index[node]:
                component = []
                while True:
                    member = stack.pop()
                    on_stack.discard(member)
                    component.append(member)
                    if member == node:
                        break
                if len(component) > 1:
                    circles.append(sorted(component))
    return sorted(circles)


def points_column_declarations(src: Path = SRC) -> list[str]:
    """Modules outside ``scanpipe/schema.py`` that spell out the points' sensor-origin column."""
    found = []
    for path in sorted(src.rglob("*.py")):
        if path.name == "schema.py":
            continue
        if re.search(r"[\"']origin_x[\"']\s*[:,)]", path.read_text()):
            found.append(module_name(path))
    return found


def canonical_name(spelling: str) -> str:
    """One idea's name whatever its dress: ``--motor-step`` and ``motor_step_deg`` are one."""
    return spelling.lstrip("-").replace("-", "_").removesuffix("_deg")


def hidden_cli_flags() -> set[str]:
    """Every hidden option of every ``scanpipe`` command: the deprecated spellings kept as
    aliases (they are there to be retired, so they do not count as names in use)."""
    import typer

    from scanpipe.cli.main import app

    def walk(command: Any) -> set[str]:  # typer's own click: duck-typed
        flags = {opt for p in command.params if getattr(p, "hidden", False)
                 for opt in getattr(p, "opts", ())}
        for sub in getattr(command, "commands", {}).values():
            flags |= walk(sub)
        return flags

    return walk(typer.main.get_command(app))


def motor_step_spellings(root: Path = ROOT) -> dict[str, int]:
    """How often each spelling of the motor step occurs in src/, README.md and docs/."""
    texts = [p.read_text() for p in [*(root / "src").rglob("*.py"), root / "README.md",
                                     *(root / "docs").glob("*.md")]]
    counts = {}
    for spelling in MOTOR_STEP_SPELLINGS:
        pattern = re.compile(rf"(?<![\w-]){re.escape(spelling)}(?![\w-])")
        counts[spelling] = sum(len(pattern.findall(t)) for t in texts)
    return {k: v for k, v in counts.items() if v}


def figures() -> dict[str, object]:
    """Every structure figure as JSON-ready values."""
    circles = import_circles(import_graph())
    declarations = points_column_declarations()
    spellings = motor_step_spellings()
    hidden = hidden_cli_flags()
    names = sorted({canonical_name(s) for s in spellings if s not in hidden})
    return {"import_circles": len(circles), "circles": circles,
            "points_column_declarations": len(declarations), "points_declared_in": declarations,
            "motor_step_names": len(names), "motor_step_canonical": names,
            "motor_step_spellings": spellings}


def main(argv: list[str] | None = None) -> int:
    """Print the figures (a table, or JSON with ``--json``)."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--json", action="store_true", help="print one JSON object")
    args = parser.parse_args(argv)
    result = figures()
    if args.json:
        print(json.dumps(result, indent=2))
        return 0
    print(f"import circles in src/: {result['import_circles']}")
    for circle in result["circles"]:  # type: ignore[attr-defined]
        print(f"  {' ↔ '.join(circle)}")
    print(f"modules declaring the points columns: {result['points_column_declarations']} "
          f"({', '.join(result['points_declared_in'])})")  # type: ignore[arg-type]
    print(f"names of the motor step: {result['motor_step_names']} "
          f"{result['motor_step_canonical']} (spellings, hidden deprecated aliases included: "
          f"{result['motor_step_spellings']})")
    return 0


if __name__ == "__main__":
    sys.exit(main())
