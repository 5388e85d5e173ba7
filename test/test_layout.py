"""
Layout rules (docs/architecture.md): no cycle, inward layers, core levels, one idea, no copies.

The import graph is read from the source: every ``import``, at module level, inside a function
or under ``if TYPE_CHECKING:`` (two modules that need each other even for annotations cannot be
read apart), with names imported through a package's re-exports resolved to their module.
"""

import ast
from collections import defaultdict
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[1] / 'coreg_ros'

#: Module size is advisory: one idea per module. Beyond ADVISED_LINES the test says so (a
#: warning, listed in the test report); beyond HARD_LINES a module certainly holds several ideas.
ADVISED_LINES = 450
HARD_LINES = 900

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


def _reexports(mods: dict) -> dict:
    """
    (package, name) -> the module that defines a name a package re-exports.

    A package's ``__init__`` re-exports names from its submodules (``from .x import name``) or
    lazily (a ``_HOMES`` dict of ``lazy_exports``); an import of the name through the package is
    an import of that module, so a cycle through a package's front is found too.
    """
    out = {}
    for pkg, path in mods.items():
        if path.name != '__init__.py':
            continue
        tree = ast.parse(path.read_text())
        for node in tree.body:
            if isinstance(node, ast.ImportFrom) and node.module and not node.level:
                for a in node.names:
                    out[(pkg, a.asname or a.name)] = node.module
            targets = node.targets if isinstance(node, ast.Assign) else []
            if any(isinstance(t, ast.Name) and t.id == '_HOMES' for t in targets):
                for key, value in zip(node.value.keys, node.value.values, strict=True):
                    home = ast.literal_eval(value)
                    home = home[0] if isinstance(home, tuple) else home
                    out[(pkg, ast.literal_eval(key))] = home if '.' in home else f'{pkg}.{home}'
    return out


def _imports(name: str, path: Path, known: set, reexports: dict = None) -> set:
    """
    Modules of the package that ``name`` imports (resolved to the deepest known module).

    Every import counts: at module level, inside a function, and under ``if TYPE_CHECKING:``
    (an annotation-only import is a dependency too: the two modules cannot be read apart).
    A name imported through a package that re-exports it resolves to its defining module.
    """
    out = set()
    reexports = reexports or {}
    package = name if path.name == '__init__.py' else name.rpartition('.')[0]
    tree = ast.parse(path.read_text())
    for node in ast.walk(tree):
        targets = []
        if isinstance(node, ast.Import):
            targets = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ''
            if node.level:
                anchor = package.split('.')[:len(package.split('.')) - node.level + 1]
                base = '.'.join(anchor + ([base] if base else []))
            targets = [reexports.get((base, a.name), f'{base}.{a.name}') for a in node.names]
            if not any(f'{base}.{a.name}' in known or (base, a.name) in reexports
                       for a in node.names):
                targets.append(base)
        for t in targets:
            while t and t not in known:
                t = t.rpartition('.')[0]
            if t and t != name and not name.startswith(t + '.'):
                out.add(t)
    return out


def import_graph() -> dict:
    """Return each module of the package with the package modules it imports (``_imports``)."""
    mods = _modules()
    known, reexports = set(mods), _reexports(mods)
    return {name: _imports(name, path, known, reexports) for name, path in mods.items()}


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
    graph = import_graph()
    # a package's __init__ re-exporting its submodules is not a cycle with them
    for name in graph:
        graph[name] = {t for t in graph[name] if not t.startswith(name + '.')}
    assert _cycles(graph) == []


def test_layers_only_point_inwards():
    """Core imports nothing of the edges; report/ and sim/ import no cli/ or ros/."""
    inner = {'coreg_ros.core': ('coreg_ros.cli', 'coreg_ros.ros', 'coreg_ros.report',
                                'coreg_ros.bag', 'coreg_ros.sim', 'coreg_ros.files'),
             'coreg_ros.report': ('coreg_ros.cli', 'coreg_ros.ros'),
             'coreg_ros.sim': ('coreg_ros.cli', 'coreg_ros.ros'),
             'coreg_ros.files': ('coreg_ros.cli', 'coreg_ros.ros'),
             'coreg_ros.parallel': ('coreg_ros.cli', 'coreg_ros.ros')}
    bad = []
    for name, targets in import_graph().items():
        for layer, forbidden in inner.items():
            if name == layer or name.startswith(layer + '.'):
                bad += [f'{name} -> {t}' for t in targets if t.startswith(forbidden)]
    assert bad == []


#: The core's levels, lowest first: a module imports only modules of its own level or below.
#: The root modules are the foundation (records, errors, quaternions, SO(3), settings, the
#: parameter schema, the models, the result text); every package of the core has one level.
CORE_LEVELS = (
    ('',),                                   # the foundation: coreg_ros/core/*.py
    ('estimator', 'noise'),                  # Ikits appendix B; a still device's noise
    ('uncertainty', 'clock'),                # Hoff & Vincent; the clock's signals and step
    ('calibration',),                        # streams and pairs to a judged result
    ('planning',),                           # the Cramér-Rao bound, a recording's plan
    ('live', 'diagnosis'),                   # guidance, watchdog, fusion; the gap diagnosis
)


def _core_level(module: str):
    """Return the level of a core module (``CORE_LEVELS``), None outside the core."""
    parts = module.split('.')
    if parts[:2] != ['coreg_ros', 'core'] or len(parts) < 3:
        return None
    package = parts[2] if (PACKAGE / 'core' / parts[2]).is_dir() else ''
    return next(i for i, names in enumerate(CORE_LEVELS) if package in names)


def test_core_levels_only_point_down():
    """Inside the core, no module imports a module of a higher level (``CORE_LEVELS``)."""
    bad = []
    for name, targets in import_graph().items():
        level = _core_level(name)
        if level is None:
            continue
        bad += [f'{name} -> {t}' for t in targets
                if (other := _core_level(t)) is not None and other > level]
    assert bad == []


def test_modules_hold_one_idea():
    """No module is a house of its own (HARD_LINES); the long ones are named (ADVISED_LINES)."""
    import warnings
    sizes = {str(p.relative_to(PACKAGE.parent)): len(p.read_text().splitlines())
             for p in PACKAGE.rglob('*.py')}
    long = {k: n for k, n in sizes.items() if n > ADVISED_LINES}
    if long:
        warnings.warn(f'modules over {ADVISED_LINES} lines (split them by idea when they grow): '
                      f'{long}', stacklevel=1)
    assert {k: n for k, n in sizes.items() if n > HARD_LINES} == {}


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
