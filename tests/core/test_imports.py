"""Layering of rfm_core: the runtime (detection, matching, mapping) never imports the
simulator, the evaluation or training, no ROS anywhere, and no module imports a module that
imports it back."""
import ast
from pathlib import Path

import pytest

PACKAGE = Path(__file__).resolve().parents[2] / 'src' / 'rfm_core' / 'rfm_core'
RUNTIME = ('detection', 'matching', 'mapping')
OFFLINE = ('rfm_core.sim', 'rfm_core.evaluation', 'rfm_core.training')


def _module(path: Path) -> str:
    parts = path.relative_to(PACKAGE.parent).with_suffix('').parts
    return '.'.join(parts[:-1] if parts[-1] == '__init__' else parts)


def _imports(path: Path, top_level_only: bool) -> set:
    """rfm_core modules ``path`` imports (anywhere, or only at module level)."""
    tree = ast.parse(path.read_text())
    nodes = tree.body if top_level_only else ast.walk(tree)
    out = set()
    for node in nodes:
        if isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out |= {f'{node.module}.{a.name}' for a in node.names}
        elif isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
    return {m for m in out if m.startswith('rfm_core')}


MODULES = {_module(p): p for p in PACKAGE.rglob('*.py')}


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
    """Module-level imports form no cycle (a cycle makes import order matter and hides
    layering mistakes)."""
    graph = {}
    for name, path in MODULES.items():
        deps = set()
        for m in _imports(path, top_level_only=True):
            while m and m not in MODULES:          # 'pkg.module.symbol' -> 'pkg.module'
                m = m.rpartition('.')[0]
            if m and m != name:
                deps.add(m)
        graph[name] = deps
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
