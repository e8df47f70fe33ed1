"""Layering of rfm_core: each layer imports only its own and lower ones (imports inside
functions count), the runtime never imports the simulator, the evaluation or training, no
ROS anywhere, and no module imports a module that imports it back."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / 'src' / 'rfm_core' / 'rfm_core'
RUNTIME = ('detection', 'matching', 'mapping')
OFFLINE = ('rfm_core.sim', 'rfm_core.evaluation', 'rfm_core.training')


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _type_checking_only(tree) -> set:
    """ids of the import nodes under ``if TYPE_CHECKING:`` (for annotations: never executed)."""
    return {id(n) for block in ast.walk(tree) if isinstance(block, ast.If)
            and getattr(block.test, 'id', None) == 'TYPE_CHECKING' for n in ast.walk(block)}


def _imports(path: Path, top_level_only: bool) -> set:
    """rfm_core modules ``path`` imports (anywhere, or only at module level), annotations aside."""
    tree = ast.parse(path.read_text())
    skip = _type_checking_only(tree)
    nodes = [n for n in (tree.body if top_level_only else ast.walk(tree)) if id(n) not in skip]
    out = set()
    for node in nodes:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out |= {f'{node.module}.{a.name}' for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return {m for m in out if m.startswith('rfm_core')}


MODULES = {_module(p): p for p in PACKAGE.rglob('*.py')}
#: lowest first: data types, then I/O, the per-frame stages, the map, the pipelines, the offline tools
LAYERS = (('rfm_core.settings', 'rfm_core.geometry', 'rfm_core.transforms', 'rfm_core.processes', 'rfm_core.inference'),
          ('rfm_core.clouds', 'rfm_core.observations'),
          ('rfm_core.io',),
          ('rfm_core.detection', 'rfm_core.matching'), ('rfm_core.mapping',),
          ('rfm_core.session', 'rfm_core.mapper_core', 'rfm_core.config'),
          ('rfm_core.sim', 'rfm_core.evaluation', 'rfm_core.training'))


def _layer(module: str) -> int | None:
    for i, names in enumerate(LAYERS):
        if any(module == n or module.startswith(n + '.') for n in names):
            return i
    return None


def _module_of(name: str) -> str:
    """'pkg.module.symbol' -> 'pkg.module'."""
    while name and name not in MODULES:
        name = name.rpartition('.')[0]
    return name


def test_every_module_has_a_layer():
    assert [m for m in MODULES if m != 'rfm_core' and _layer(m) is None] == []


@pytest.mark.parametrize('name', sorted(m for m in MODULES if m != 'rfm_core'))
def test_no_module_imports_a_higher_layer(name):
    """Also imports inside functions: a lazy import hides a dependency, it does not remove it."""
    up = sorted({d for d in map(_module_of, _imports(MODULES[name], top_level_only=False))
                 if d and _layer(d) > _layer(name)})
    assert not up, f'{name} (layer {_layer(name)}) imports {up}'


@pytest.mark.parametrize('name', sorted(m for m in MODULES if m.split('.')[1:2] and m.split('.')[1] in RUNTIME))
def test_runtime_modules_import_no_simulator_evaluation_or_training(name):
    bad = sorted(m for m in _imports(MODULES[name], top_level_only=False) if m.startswith(OFFLINE))
    assert not bad, f'{name} imports {bad}'


def test_rfm_core_has_no_ros_imports():
    for name, path in MODULES.items():
        tree = ast.parse(path.read_text())
        roots = {a.name.split('.')[0] for n in ast.walk(tree) if isinstance(n, ast.Import) for a in n.names}
        roots |= {n.module.split('.')[0] for n in ast.walk(tree) if isinstance(n, ast.ImportFrom) and n.module}
        assert not roots & {'rclpy', 'rfm_msgs', 'sensor_msgs', 'geometry_msgs', 'tf2_ros'}, name


def test_no_import_cycles():
    """Imports, anywhere in a module, form no cycle (a cycle makes import order matter and
    hides layering mistakes)."""
    graph = {}
    for name, path in MODULES.items():
        graph[name] = {m for m in map(_module_of, _imports(path, top_level_only=False)) if m and m != name}
    state, stack = {}, []

    def visit(node):
        state[node] = 'open'
        stack.append(node)
        for dep in sorted(graph.get(node, ())):
            if state.get(dep) == 'open':
                cycle = stack[stack.index(dep):] + [dep]
                raise AssertionError('import cycle: ' + ' -> '.join(cycle))
            if dep not in state:
                visit(dep)
        stack.pop()
        state[node] = 'done'

    for node in sorted(graph):
        if node not in state:
            visit(node)


def test_nodes_only_translate_messages():
    """The nodes wire topics and services to rfm_core and translate messages; what they decide
    lives in the core (the mapper's in rfm_core.mapper_core)."""
    src = PACKAGE.parents[1]
    lines = {name: len((src / f'rfm_{name}_node' / f'rfm_{name}_node' / f'{name}_node.py').read_text().splitlines())
             for name in ('detector', 'matcher', 'mapper')}
    assert lines['mapper'] <= 150 and max(lines.values()) <= 200, lines
