"""
Layout rules (docs/architecture.md): no import cycle, inward layers, small modules, no copies.

The import graph is read from the source (every ``import``, at module level or inside a
function, but not under ``if TYPE_CHECKING:``), so a cycle hidden in a function-level import is
found too.
"""

import ast
from collections import defaultdict
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'coreg_ros'

#: The size a module may have (lines); a module beyond it is split by idea.
MAX_LINES = 450

#: Bodies shorter than this many statements may repeat (a guard clause, a one-line wrapper).
MIN_COPIED_STATEMENTS = 4


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


def test_modules_are_small():
    big = {str(p.relative_to(PACKAGE.parent)): n for p in PACKAGE.rglob('*.py')
           if (n := len(p.read_text().splitlines())) > MAX_LINES}
    assert big == {}


def test_core_gives_each_name_one_meaning():
    """No two functions or classes of the numerical core share a name (one home, one meaning)."""
    homes = defaultdict(list)
    for path in (PACKAGE / 'core').rglob('*.py'):
        for node in ast.parse(path.read_text()).body:
            named = isinstance(node, (ast.FunctionDef, ast.ClassDef))
            if named and not node.name.startswith('__'):
                homes[node.name].append(str(path.relative_to(PACKAGE)))
    assert {k: v for k, v in homes.items() if len(v) > 1} == {}


class _Shape(ast.NodeTransformer):
    """Forget names and constants: two bodies of the same shape are the same logic copied."""

    def visit_Name(self, node):
        return ast.copy_location(ast.Name(id='_', ctx=node.ctx), node)

    def visit_arg(self, node):
        return ast.copy_location(ast.arg(arg='_'), node)

    def visit_Constant(self, node):
        return ast.copy_location(ast.Constant(value=None), node)


def _body_shape(fn: ast.FunctionDef):
    body = fn.body
    if body and isinstance(body[0], ast.Expr) and isinstance(body[0].value, ast.Constant):
        body = body[1:]  # the docstring
    statements = sum(isinstance(n, ast.stmt) for b in body for n in ast.walk(b))
    if statements < MIN_COPIED_STATEMENTS:
        return None
    return ast.dump(_Shape().visit(ast.Module(body=[ast.parse(ast.unparse(b)).body[0]
                                                    for b in body], type_ignores=[])))


def test_no_function_body_is_copied():
    """No two functions of the package have the same body up to names and constants."""
    shapes = defaultdict(list)
    for path in PACKAGE.rglob('*.py'):
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.FunctionDef) and (shape := _body_shape(node)) is not None:
                shapes[shape].append(f'{path.relative_to(PACKAGE)}:{node.lineno} {node.name}')
    assert [v for v in shapes.values() if len(v) > 1] == []
