"""
The package's layout rules (docs/architecture.md): no import cycle, and layers that point inwards.

The import graph is read from the source (every ``import``, at module level or inside a
function, but not under ``if TYPE_CHECKING:``), so a cycle hidden in a function-level import is
found too.
"""

import ast
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'coreg_ros'


def _modules() -> dict:
    mods = {}
    for path in PACKAGE.rglob('*.py'):
        rel = path.relative_to(PACKAGE.parent).with_suffix('')
        parts = list(rel.parts)
        if parts[-1] == '__init__':
            parts = parts[:-1]
        mods['.'.join(parts)] = path
    return mods


def _imports(name: str, path: Path, known: set) -> set:
    """Modules of the package that ``name`` imports (resolved to the deepest known module)."""
    out = set()
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    tree = ast.parse(path.read_text())
    typing_only = {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
                   and 'TYPE_CHECKING' in ast.unparse(block.test) for n in ast.walk(block)}
    for node in ast.walk(tree):
        targets = []
        if id(node) in typing_only:  # annotations only: not an import at run time
            continue
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(anchor + ([base] if base else []))
            targets = [f'{base}.{a.name}' for a in node.names] + [base]
        for t in targets:
            while t and t not in known:
                t = t.rpartition('.')[0]
            if t and t != name and not name.startswith(t + '.'):
                out.add(t)
    return out


def _cycles(graph: dict) -> list:
    """Strongly connected components with more than one module (Tarjan)."""
    index, low, stack, on, comps, counter = {}, {}, [], set(), [], [0]

    def visit(v):
        index[v] = low[v] = counter[0]
        counter[0] += 1
        stack.append(v)
        on.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
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
                comps.append(sorted(comp))

    for v in graph:
        if v not in index:
            visit(v)
    return comps


def test_no_import_cycle():
    mods = _modules()
    graph = {name: _imports(name, path, set(mods)) for name, path in mods.items()}
    # a package's __init__ re-exporting its submodules is not a cycle with them
    for name in graph:
        graph[name] = {t for t in graph[name] if not t.startswith(name + '.')}
    assert _cycles(graph) == []


def test_layers_only_point_inwards():
    """Core imports nothing of the edges; report/ and sim/ import no cli/ or ros/."""
    mods = _modules()
    inner = {'coreg_ros.core': ('coreg_ros.cli', 'coreg_ros.ros', 'coreg_ros.report',
                                'coreg_ros.bag', 'coreg_ros.sim', 'coreg_ros.files'),
             'coreg_ros.report': ('coreg_ros.cli', 'coreg_ros.ros'),
             'coreg_ros.sim': ('coreg_ros.cli', 'coreg_ros.ros')}
    bad = []
    for name, path in mods.items():
        for layer, forbidden in inner.items():
            if name == layer or name.startswith(layer + '.'):
                bad += [f'{name} -> {t}' for t in _imports(name, path, set(mods))
                        if t.startswith(forbidden)]
    assert bad == []
