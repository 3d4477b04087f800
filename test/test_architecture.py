"""Dependencies point inward, and the folders say how.

The package's folders are its wings, from the inside out; a module may import
its own wing and the wings inside it, never one further out or beside it. The
rank of each wing is the one table kept by hand; which module belongs to which
wing is read from the folders, and the imports from the code (``ast``).
"""
import ast
import subprocess
import sys
from pathlib import Path

import pytest

import has_control

PACKAGE = Path(has_control.__file__).resolve().parent

#: Each wing and its rank: a wing may import only wings of lower rank (and itself).
WINGS = {
    "common": 0,    # errors, files, JSON numbers: what every wing shares
    "core": 1,      # the physics, the law, the cost, the episode kernels: no ROS, no bags, no files
    "config": 2,    # YAML and ros__parameters files into core's typed parameters
    "wire": 2,      # topics, CDR codecs, one sample of plant or controller on serialized bytes
    "bag": 3,       # rosbag2 MCAP: write, read, score
    "plots": 4,     # figures
    "tuning": 5,    # optimisers, sessions, robustness, the paper experiment, Dask
    "identify": 5,  # plant parameters from recorded runs: reads bags, simulates with core (beside tuning)
    "deploy": 5,    # guarded deployment: the watchdog and the stepped move to tuned gains (beside tuning)
    "loop": 5,      # the sample loop without ROS: plant and controller processes, guards, ports, schedules
    "nodes": 6,     # the ROS layer
    "bench": 7,     # benchmarks
    "cli": 8,       # the command line and the demo
}
ROS = ("rclpy", "sensor_msgs", "std_msgs", "rosgraph_msgs", "diagnostic_msgs", "std_srvs", "lifecycle_msgs")
BAGS = ("rosbags", "mcap")
#: What each wing may not load, directly or through another module.
BANNED = {"common": ROS + BAGS, "core": ROS + BAGS, "config": ROS + BAGS, "wire": ROS + BAGS,
          "bag": ROS, "plots": ROS, "tuning": ROS, "identify": ROS, "deploy": ROS,
          "loop": ROS + BAGS}


def _modules():
    """(dotted name, wing, path) of every module of the package below a wing."""
    for path in sorted(PACKAGE.rglob("*.py")):
        rel = path.relative_to(PACKAGE)
        if len(rel.parts) == 1:
            continue                                      # has_control/__init__.py: the public API
        parts = list(rel.with_suffix("").parts)
        if parts[-1] == "__init__":
            parts.pop()
        yield "has_control." + ".".join(parts), rel.parts[0], path


def _imports(path: Path, module: str, top_level_only: bool = False):
    """(line, imported has_control module or package, is at module level) of one file."""
    tree = ast.parse(path.read_text())
    package = module if path.name == "__init__.py" else module.rpartition(".")[0]
    top = {id(n) for n in tree.body}
    for node in ast.walk(tree):
        at_top = id(node) in top
        if top_level_only and not at_top:
            continue
        if isinstance(node, ast.Import):
            names = [a.name for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                parts = package.split(".")
                base = ".".join(parts[:len(parts) - node.level + 1] + ([base] if base else []))
            names = [base] + [f"{base}.{a.name}" for a in node.names]
        else:
            continue
        for name in names:
            if name.startswith("has_control."):
                yield node.lineno, name, at_top


def _wing(name: str) -> str | None:
    parts = name.split(".")
    return parts[1] if len(parts) > 1 and parts[1] in WINGS else None


def test_every_folder_is_a_wing_and_every_module_sits_in_one():
    folders = {p.name for p in PACKAGE.iterdir() if p.is_dir() and p.name != "__pycache__"}
    assert folders == set(WINGS)
    loose = sorted(p.name for p in PACKAGE.glob("*.py") if p.name != "__init__.py")
    assert loose == []


def test_no_module_imports_a_wing_further_out_or_beside_its_own():
    wrong = []
    for module, wing, path in _modules():
        for line, name, _ in _imports(path, module):
            other = _wing(name)
            if other and other != wing and WINGS[other] >= WINGS[wing]:
                wrong.append(f"{path.relative_to(PACKAGE)}:{line} ({wing}) imports {name} ({other})")
    assert wrong == []


def test_no_module_imports_the_root_package():
    """``has_control/__init__.py`` is the public API over the wings: a module
    inside a wing that imports it (``import has_control``, ``from has_control
    import X``) makes a cycle that the dotted-name checks above do not see."""
    wrong = []
    for module, _, path in _modules():
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import) and any(a.name == "has_control" for a in node.names):
                wrong.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
            elif isinstance(node, ast.ImportFrom) and node.module == "has_control" and not node.level:
                wrong.append(f"{path.relative_to(PACKAGE)}:{node.lineno}")
    assert wrong == []


def test_every_cached_kernel_is_keyed_by_every_compiled_source():
    """A module whose compiled functions are cached on disk (``core.jit``'s
    options, or ``cache=True``) calls the core's functions, which numba inlines:
    unless it is one of ``COMPILED_MODULES`` its cache outlives an edit to them
    (a stale kernel: same numbers, other code)."""
    cached = set()
    for module, _, path in _modules():
        decorators = [line.strip() for line in path.read_text().splitlines() if line.strip().startswith("@")]
        if any("jit(" in d and ("cache=True" in d or "KERNEL" in d or "INLINE" in d or "LEAF" in d)
               for d in decorators):
            cached.add(module.removeprefix("has_control."))
    assert sorted(cached - set(has_control.COMPILED_MODULES)) == []


def _assert_no_cycle(top_level_only: bool) -> None:
    """No import cycle among the package's modules (a module's own packages,
    which Python loads before it, are not an edge)."""
    graph = {}
    known = {m for m, _, _ in _modules()}
    for module, _, path in _modules():
        graph[module] = {n for _, n, _ in _imports(path, module, top_level_only=top_level_only)
                         if n in known and not module.startswith(n + ".")} - {module}
    state = {}

    def visit(m, stack):
        state[m] = "open"
        for n in sorted(graph.get(m, ())):
            if state.get(n) == "open":
                raise AssertionError("import cycle: " + " -> ".join(stack[stack.index(n):] + [n]))
            if n not in state:
                visit(n, stack + [n])
        state[m] = "done"

    for m in sorted(graph):
        if m not in state:
            visit(m, [m])


def test_no_import_cycles():
    _assert_no_cycle(top_level_only=True)


def test_no_import_cycles_through_function_level_imports():
    """A lazy import is for start-up time or an optional dependency, never to
    hide a cycle (nodes.foxglove and nodes.live_process imported each other)."""
    _assert_no_cycle(top_level_only=False)


def test_function_level_imports_state_their_reason():
    """An import inside a function is there for a reason (start-up time, an
    optional dependency; never a cycle): a comment on its line, or on the line above
    the run of import lines it belongs to, says which."""
    silent = []
    for module, _, path in _modules():
        lines = path.read_text().split("\n")
        for line, name, at_top in _imports(path, module):
            if at_top or "#" in lines[line - 1]:
                continue
            above = line - 2
            while above >= 0 and lines[above].strip().startswith(("from ", "import ")):
                above -= 1
            if above < 0 or not lines[above].strip().startswith("#"):
                silent.append(f"{path.relative_to(PACKAGE)}:{line}: {lines[line - 1].strip()}")
    assert sorted(set(silent)) == []


def _loaded_by(modules, banned) -> str:
    code = ("import sys\n"
            + "".join(f"import {m}\n" for m in modules)
            + f"bad = sorted(m for m in sys.modules if m.split('.')[0] in {banned!r})\n"
            + "print(','.join(bad))")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()


@pytest.mark.system
def test_inner_wings_load_no_ros_and_no_bags():
    for wing, banned in BANNED.items():
        modules = [m for m, w, p in _modules() if w == wing and p.name != "__main__.py"]
        assert _loaded_by(modules, banned) == "", wing


@pytest.mark.compile
def test_editing_a_callee_module_recompiles_the_kernels(tmp_path):
    """numba alone would keep episode's cached kernel after actuator.py changes."""
    import shutil

    pkg = tmp_path / "has_control"
    shutil.copytree(PACKAGE, pkg, ignore=shutil.ignore_patterns("__pycache__"))
    code = ("import has_control.core.episode as e; from has_control.config import with_horizon;"
            "e.simulate(with_horizon(e.Config(), 1.5));"
            "print(e._episode._cache._cache_path)")
    env = {"PYTHONPATH": str(tmp_path), "PATH": "/usr/bin:/bin"}

    def cache_path():
        return subprocess.run([sys.executable, "-c", code], cwd=tmp_path, env=env,
                              capture_output=True, text=True, check=True).stdout.strip()
    first = cache_path()
    assert first == cache_path()                       # unchanged sources: the cache is reused
    with open(pkg / "core" / "actuator.py", "a") as f:
        f.write("\n# an edit to the physics\n")
    assert cache_path() != first


def test_every_compiled_callee_is_in_the_cache_key():
    """The kernels' cache is keyed by the sources of COMPILED_MODULES: a module
    with compiled functions that one of them imports (core.road's sum, inlined
    into the reference) must be among them, or an edit to it runs a stale kernel."""
    compiled = {f"has_control.{m}" for m in has_control.COMPILED_MODULES}
    paths = {m: p for m, _, p in _modules()}
    missing = set()
    for module in compiled:
        for _, name, _ in _imports(paths[module], module):
            callee = name if name in paths else name.rpartition(".")[0]
            if callee in paths and callee not in compiled and "@njit" in paths[callee].read_text():
                missing.add(callee)
    assert not missing, f"compiled modules missing from has_control.COMPILED_MODULES: {sorted(missing)}"
