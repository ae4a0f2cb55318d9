"""Every public function and method of the package carries type hints: its arguments and its return.

Public means a name without a leading underscore, at module level or in a public class, in a module whose own
name is public. `self`/`cls`, `*args`/`**kwargs` and `__init__`'s return are exempt. Read from the source with
`ast`, so nothing is imported.
"""

import ast
from pathlib import Path

import mvrecon

PACKAGE = Path(mvrecon.__file__).resolve().parent


def _unannotated(tree: ast.AST) -> list[tuple[str, int]]:
    out = []

    def visit(node: ast.AST, public: bool, prefix: str) -> None:
        for child in ast.iter_child_nodes(node):
            if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)):
                if not public or (child.name.startswith("_") and child.name != "__init__"):
                    continue
                args = [a for a in child.args.posonlyargs + child.args.args + child.args.kwonlyargs
                        if a.arg not in ("self", "cls")]
                missing = [a.arg for a in args if a.annotation is None]
                if child.returns is None and child.name != "__init__":
                    missing.append("return")
                if missing:
                    out.append((f"{prefix}{child.name} ({', '.join(missing)})", child.lineno))
            elif isinstance(child, ast.ClassDef):
                visit(child, public and not child.name.startswith("_"), f"{prefix}{child.name}.")

    visit(tree, True, "")
    return out


def test_public_functions_carry_type_hints():
    found = []
    for path in sorted(PACKAGE.rglob("*.py")):
        if any(part.startswith("_") and part != "__init__.py" for part in path.relative_to(PACKAGE).parts):
            continue
        for what, line in _unannotated(ast.parse(path.read_text(), str(path))):
            found.append(f"{path.relative_to(PACKAGE.parent)}:{line}: {what}")
    assert not found, "public functions without type hints:\n" + "\n".join(found)
