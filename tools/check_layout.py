# SPDX-License-Identifier: Apache-2.0
"""The package's layout rules, checked from the source (no import of the package).

    python tools/check_layout.py [ROOT]     # prints every finding, exit 1 if any

Rules (docs/maintainers.md explains them; test/test_layout.py asserts each):

- ``file_size``: no product file (``ae_tactile/**.py``) over ``MAX_FILE_LINES`` lines unless
  one of its first 3 lines is a ``# size: <reason>`` comment;
- ``function_size``: no function over ``MAX_FUNCTION_LINES`` lines or with blocks nested
  deeper than ``MAX_NESTING`` (an ``elif`` is not a level) unless it is a numba kernel
  (``@njit`` / ``@jit``) or carries ``# size: <reason>`` before its first statement;
- ``spdx``: every source file starts with an SPDX licence line (after a shebang);
- ``import_cycle``: no cycle among the package's imports (those inside functions too);
- ``layering``: no import from a lower layer of the data flow to a higher one
  (``LAYERS``), no rclpy outside ``ae_tactile.ros``, no ``ae_eval`` in the product;
- ``lazy_import``: an import inside a function says why with a ``lazy`` comment.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

MAX_FILE_LINES = 600
MAX_FUNCTION_LINES = 80
MAX_NESTING = 4
PACKAGE = "ae_tactile"

#: rank of each top-level part of the package along the data flow: a module may import
#: from its own rank or below, never from above
LAYERS = {
    "geometry": 0, "records": 0, "jit": 0, "protocol": 0, "calibration": 0,
    "dsp": 1, "localization": 1, "sim": 1,
    "slip": 2,
    "pipeline": 3,
    "timesync": 4, "link": 4, "virtual_device": 4, "device": 4, "bagtools": 4, "report": 4,
    "evaluation": 4, "scoring": 4, "recordings": 4, "compile_kernels": 4,
    "ros": 5,
}
_BLOCKS = (ast.If, ast.For, ast.AsyncFor, ast.While, ast.With, ast.AsyncWith, ast.Try,
           ast.Match) + ((ast.TryStar,) if hasattr(ast, "TryStar") else ())
_SOURCE_SUFFIXES = (".py", ".sh")
_SOURCE_NAMES = ("Makefile", "CMakeLists.txt", "run")


def tracked_files(root: Path) -> list[Path]:
    """The files git tracks plus the untracked ones it does not ignore."""
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard"],
                         cwd=root, capture_output=True, text=True, check=True).stdout
    return [root / f for f in out.splitlines() if (root / f).is_file()]


def is_source(path: Path, root: Path) -> bool:
    rel = path.relative_to(root)
    if rel.parts[0] in ("scripts",) and not path.suffix:
        return True
    return path.suffix in _SOURCE_SUFFIXES or path.name in _SOURCE_NAMES


def product_modules(root: Path) -> dict[str, Path]:
    """Dotted module name -> file, for every module of the installed package."""
    mods = {}
    for path in sorted((root / PACKAGE).rglob("*.py")):
        parts = list(path.relative_to(root).with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        mods[".".join(parts)] = path
    return mods


def check_spdx(root: Path) -> list[str]:
    bad = []
    for path in tracked_files(root):
        if not is_source(path, root):
            continue
        head = path.read_text(encoding="utf-8", errors="replace").splitlines()[:3]
        if not any("SPDX-License-Identifier:" in line for line in head):
            bad.append(f"spdx: {path.relative_to(root)} has no SPDX line in its first lines")
    return bad


def check_file_size(root: Path) -> list[str]:
    bad = []
    for path in product_modules(root).values():
        lines = path.read_text(encoding="utf-8").splitlines()
        if len(lines) > MAX_FILE_LINES and not any(
                line.startswith("# size:") for line in lines[:3]):
            bad.append(f"file_size: {path.relative_to(root)} has {len(lines)} lines "
                       f"(> {MAX_FILE_LINES}, no '# size:' reason in its first 3 lines)")
    return bad


def _nesting(node: ast.AST, depth: int = 0) -> int:
    """Deepest block nesting below node, not entering nested functions or classes."""
    deepest = depth
    for child in ast.iter_child_nodes(node):
        if isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef, ast.ClassDef, ast.Lambda)):
            continue
        if isinstance(child, _BLOCKS):
            level = depth + 1
            if (isinstance(child, ast.If) and isinstance(node, ast.If)
                    and node.orelse == [child]):
                level = depth  # an elif: the same level as its if
            deepest = max(deepest, _nesting(child, level))
        else:
            deepest = max(deepest, _nesting(child, depth))
    return deepest


def _exempt(fn, lines: list[str]) -> bool:
    for dec in fn.decorator_list:
        target = dec.func if isinstance(dec, ast.Call) else dec
        name = target.attr if isinstance(target, ast.Attribute) else getattr(target, "id", "")
        if name in ("njit", "jit", "vectorize", "guvectorize"):
            return True
    body = fn.body
    first = body[0]
    if (len(body) > 1 and isinstance(first, ast.Expr)
            and isinstance(first.value, ast.Constant) and isinstance(first.value.value, str)):
        first = body[1]
    return any("# size:" in line for line in lines[fn.lineno - 1:first.lineno])


def check_functions(root: Path) -> list[str]:
    bad = []
    for path in product_modules(root).values():
        text = path.read_text(encoding="utf-8")
        lines = text.splitlines()
        for fn in ast.walk(ast.parse(text)):
            if not isinstance(fn, (ast.FunctionDef, ast.AsyncFunctionDef)) or _exempt(fn, lines):
                continue
            where = f"{path.relative_to(root)}:{fn.lineno} {fn.name}"
            n = fn.end_lineno - fn.lineno + 1
            if n > MAX_FUNCTION_LINES:
                bad.append(f"function_size: {where} has {n} lines (> {MAX_FUNCTION_LINES})")
            depth = _nesting(fn)
            if depth > MAX_NESTING:
                bad.append(f"function_size: {where} nests {depth} deep (> {MAX_NESTING})")
    return bad


def _imports(tree: ast.AST, module: str, is_package: bool, mods):
    """(imported module, line, inside a function) for each import of the tree."""
    out = []

    def visit(node, in_function):
        for child in ast.iter_child_nodes(node):
            inner = in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef))
            if isinstance(child, ast.Import):
                out.extend((a.name, child.lineno, in_function) for a in child.names)
            elif isinstance(child, ast.ImportFrom):
                base = child.module or ""
                if child.level:
                    pkg = module.split(".") if is_package else module.split(".")[:-1]
                    pkg = pkg[:len(pkg) - (child.level - 1)]
                    base = ".".join(pkg + ([base] if base else []))
                for a in child.names:
                    sub = f"{base}.{a.name}"
                    out.append((sub if sub in mods else base, child.lineno, in_function))
            visit(child, inner)

    visit(tree, False)
    return out


def import_graph(root: Path):
    """module -> [(imported module, line, inside a function)] for the package's modules."""
    mods = product_modules(root)
    graph = {}
    for name, path in mods.items():
        tree = ast.parse(path.read_text(encoding="utf-8"))
        graph[name] = _imports(tree, name, path.name == "__init__.py", mods)
    return graph, mods


def _cycles(edges: dict[str, set]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, out = {}, {}, [], set(), []

    def strong(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on.add(v)
        for w in edges.get(v, ()):
            if w not in index:
                strong(w)
                low[v] = min(low[v], low[w])
            elif w in on:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            comp = []
            while True:
                w = stack.pop()
                on.discard(w)
                comp.append(w)
                if w == v:
                    break
            if len(comp) > 1:
                out.append(sorted(comp))

    # the recursion goes as deep as the longest import chain (tens of modules): the limit is
    # raised for this call only (a raised limit left behind changes other code's behaviour,
    # e.g. how deep a YAML document may nest before it is refused)
    limit = sys.getrecursionlimit()
    sys.setrecursionlimit(max(10_000, limit))
    try:
        for v in sorted(edges):
            if v not in index:
                strong(v)
    finally:
        sys.setrecursionlimit(limit)
    return out


def check_imports(root: Path) -> list[str]:
    graph, mods = import_graph(root)
    bad = []
    # every import counts, those inside functions too: a lazy import does not make a cycle
    # go away, it only hides it
    edges = {m: {t for t, _, _ in imps if t in mods and t != m} for m, imps in graph.items()}
    for comp in _cycles(edges):
        bad.append("import_cycle: " + " <-> ".join(comp))
    for m, imps in graph.items():
        path = mods[m].relative_to(root)
        src = mods[m].read_text(encoding="utf-8").splitlines()
        part = m.split(".")[1] if "." in m else ""
        for target, line, in_function in imps:
            top = target.split(".")[0]
            if top == "ae_eval":
                bad.append(f"layering: {path}:{line} imports the evaluation package ae_eval")
            if top in ("rclpy", "rclpy_message_converter") and part != "ros":
                bad.append(f"layering: {path}:{line} imports rclpy outside ae_tactile.ros")
            if top == PACKAGE and "." in target:
                other = target.split(".")[1]
                if LAYERS.get(other, 0) > LAYERS.get(part, 5):
                    bad.append(f"layering: {path}:{line} ({part}) imports {target} "
                               f"from a higher layer")
            if in_function and not any("lazy" in s for s in src[max(0, line - 2):line]):
                bad.append(f"lazy_import: {path}:{line} imports {target} inside a function "
                           f"without a '# lazy: <reason>' comment")
    return bad


CHECKS = {
    "spdx": check_spdx,
    "file_size": check_file_size,
    "function_size": check_functions,
    "imports": check_imports,
}


def main(argv=None) -> int:
    root = Path((argv or sys.argv[1:] or [Path(__file__).resolve().parents[1]])[0]).resolve()
    found = [p for check in CHECKS.values() for p in check(root)]
    print("\n".join(found) if found else "layout: no findings")
    return 1 if found else 0


if __name__ == "__main__":
    sys.exit(main())
