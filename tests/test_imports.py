"""The house's import rules, read from the source (imports inside functions count too): the data layer never
imports the method, and the data layer's modules import each other without a circle."""

from __future__ import annotations

import ast
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def imported_modules(path: Path) -> set[str]:
    """Every module a file imports, at any depth of its code (``from a.b import c`` gives ``a.b``, and ``a.b.c``
    in case ``c`` is a submodule)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.Import):
            out.update(alias.name for alias in node.names)
        elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
            out.add(node.module)
            out.update(f"{node.module}.{alias.name}" for alias in node.names)
    return out


def assert_no_circle(graph: dict[str, set[str]]) -> None:
    """Depth-first search of ``module -> modules it imports``; fails naming the first circle found."""
    state: dict[str, int] = {}

    def visit(name: str, path: list[str]) -> None:
        state[name] = 1
        for dep in sorted(graph[name]):
            assert state.get(dep) != 1, f"import circle: {' -> '.join(path + [name, dep])}"
            if dep not in state:
                visit(dep, path + [name])
        state[name] = 2

    for name in sorted(graph):
        if name not in state:
            visit(name, [])


def data_graph() -> dict[str, set[str]]:
    files = {f"datamodules.{p.stem}": p for p in (ROOT / "datamodules").glob("*.py") if p.stem != "__init__"}
    return {name: {m for m in imported_modules(p) if m in files} for name, p in files.items()}


def test_data_never_imports_the_method():
    for path in sorted((ROOT / "datamodules").glob("*.py")):
        method = sorted(m for m in imported_modules(path) if m == "ssm_ms" or m.startswith("ssm_ms."))
        assert not method, f"{path.name} imports {method}: data must not depend on the method"


def test_data_modules_import_each_other_without_a_circle():
    graph = data_graph()
    assert graph["datamodules.base"] >= {"datamodules.arrays", "datamodules.samplers"}  # the graph is read
    assert_no_circle(graph)


def test_the_circle_check_finds_a_circle(monkeypatch):
    """The check itself: a graph with base -> files -> base is refused."""
    import pytest

    fake = {"datamodules.base": {"datamodules.files", "datamodules.arrays", "datamodules.samplers"},
            "datamodules.files": {"datamodules.base"}, "datamodules.arrays": set(), "datamodules.samplers": set()}
    monkeypatch.setitem(globals(), "data_graph", lambda: fake)
    with pytest.raises(AssertionError, match="import circle"):
        test_data_modules_import_each_other_without_a_circle()


def method_graph() -> dict[str, set[str]]:
    """``ssm_ms``'s modules -> the ``ssm_ms`` modules each imports (a package's own parents left out: importing
    ``ssm_ms.nets.native`` loads ``ssm_ms.nets`` first, which is not a circle)."""
    files = {}
    for p in (ROOT / "ssm_ms").rglob("*.py"):
        parts = p.relative_to(ROOT).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return {name: {d for d in imported_modules(path) if d in files and d != name and not name.startswith(d + ".")}
            for name, path in files.items()}


def test_the_method_imports_without_a_circle():
    graph = method_graph()
    assert "ssm_ms.nets.native.build" in graph["ssm_ms.nets.native.ops"]  # the graph is read
    assert_no_circle(graph)


def test_moved_modules_keep_their_old_names():
    """Configs and checkpoints of earlier versions name ``ssm_ms.nets.observation.*``: those names still load, as
    the same classes."""
    import importlib

    from ssm_ms import nets

    old = importlib.import_module("ssm_ms.nets.observation")
    for name in ("ConvDecoder", "LinearReadout", "Projection"):
        assert getattr(old, name) is getattr(nets, name)
    from ssm_ms import export

    control = importlib.import_module("ssm_ms.control")  # the export module's earlier name
    for name in ("export", "export_checkpoint", "linearize", "main"):
        assert getattr(control, name) is getattr(export, name)


def test_the_old_export_command_still_runs():
    import subprocess
    import sys

    out = subprocess.run([sys.executable, "-m", "ssm_ms.control", "export", "--help"], cwd=ROOT, capture_output=True,
                         text=True)
    assert out.returncode == 0 and "--out" in out.stdout, out.stderr


def test_the_forecasting_modules_keep_their_old_names():
    """``ssm_ms.evaluation``, ``ssm_ms.predict`` and ``ssm_ms.results`` moved into ``ssm_ms.forecasting``; a command
    line naming ``ssm_ms.predict.ForecastWriter`` and code importing the old modules still work."""
    import importlib

    from ssm_ms import forecasting
    from ssm_ms.forecasting import protocol, results

    assert importlib.import_module("ssm_ms.predict").ForecastWriter is forecasting.ForecastWriter
    old = importlib.import_module("ssm_ms.evaluation")
    for name in ("ForecastModule", "Forecast", "ValidTimeAccumulator", "split_sequence", "mse_per_sequence"):
        assert getattr(old, name) is getattr(protocol, name)
    old = importlib.import_module("ssm_ms.results")
    for name in ("PAPER", "write_results", "write_pipeline", "render_markdown"):
        assert getattr(old, name) is getattr(results, name)


def test_drawing_is_apart_from_the_callbacks():
    """``ssm_ms.drawing`` draws without Lightning; ``ssm_ms.viz`` keeps the callbacks the configs name and, for code
    of earlier versions, the drawing functions under their old names (the same functions)."""
    import importlib

    from ssm_ms import drawing

    lightning = sorted(m for m in imported_modules(ROOT / "ssm_ms" / "drawing.py") if m.split(".")[0] == "lightning")
    assert not lightning, f"ssm_ms/drawing.py imports {lightning}"
    viz = importlib.import_module("ssm_ms.viz")
    public = [n for n, v in vars(drawing).items() if callable(v) and not n.startswith("_")
              and getattr(v, "__module__", None) == "ssm_ms.drawing"]
    assert "prediction_mosaic" in public and "shooting_figure" in public
    for name in public:
        assert getattr(viz, name) is getattr(drawing, name), name
    assert {"ReconstructionLogger", "ShootingPictureLogger"} <= set(vars(viz))
