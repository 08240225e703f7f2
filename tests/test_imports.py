"""The house's import rules, read from the source (imports inside functions count too): the data layer never
imports the method, and the data layer's modules import each other without a circle; the application
(``experiments/``) sits above both, and neither imports it."""

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


def test_the_data_set_and_the_normalizer_sit_below_the_datamodule():
    """base.py's DataModule builds on dataset.py (the array data set), normalizer.py and predict.py (the files to
    forecast), never the other way round."""
    graph = data_graph()
    assert graph["datamodules.base"] >= {"datamodules.dataset", "datamodules.normalizer", "datamodules.predict"}
    assert graph["datamodules.predict"] == {"datamodules.arrays", "datamodules.dataset"}
    assert graph["datamodules.dataset"] == {"datamodules.normalizer"}
    assert graph["datamodules.normalizer"] == set()


def test_the_circle_check_finds_a_circle(monkeypatch):
    """The check itself: a graph with base -> files -> base is refused."""
    import pytest

    fake = {
        "datamodules.base": {"datamodules.files", "datamodules.arrays", "datamodules.samplers"},
        "datamodules.files": {"datamodules.base"},
        "datamodules.arrays": set(),
        "datamodules.samplers": set(),
    }
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
    return {
        name: {d for d in imported_modules(path) if d in files and d != name and not name.startswith(d + ".")}
        for name, path in files.items()
    }


def test_the_method_imports_without_a_circle():
    graph = method_graph()
    assert "ssm_ms.nets.native.build" in graph["ssm_ms.nets.native.ops"]  # the graph is read
    assert_no_circle(graph)


def test_drawing_is_apart_from_the_callbacks():
    """``ssm_ms.drawing`` draws without Lightning; ``ssm_ms.viz`` holds the callbacks the configs name."""
    import importlib

    lightning = sorted(m for m in imported_modules(ROOT / "ssm_ms" / "drawing.py") if m.split(".")[0] == "lightning")
    assert not lightning, f"ssm_ms/drawing.py imports {lightning}"
    assert {"ReconstructionLogger", "ShootingPictureLogger"} <= set(vars(importlib.import_module("ssm_ms.viz")))


def test_the_pipeline_and_the_results_files_start_without_lightning_or_torch():
    """``python -m experiments.reproduce`` only runs stages, and the results and README tools only read JSON: none
    of them pays Lightning's and torch's imports (~10 s on a slow 2-core CPU) before its first line of work."""
    import subprocess
    import sys

    script = (
        "import sys, experiments.reproduce, experiments.results, experiments.readme, experiments.cli, "
        "experiments.registry, experiments.benchmark_results\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'torch', 'torchmetrics'}))"
    )
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == "[]", out.stdout + out.stderr


def test_a_filter_imports_without_lightning():
    """``ssm_ms.inference`` names its classes lazily: the UKF and the particle filter (what the control loop's
    estimators and ``benchmarks/bench_ukf.py`` load) come without Lightning; the package's names still resolve."""
    import subprocess
    import sys

    script = (
        "import sys, ssm_ms.inference.ukf, ssm_ms.inference.particle\n"
        "print(sorted({m.split('.')[0] for m in sys.modules} & {'lightning', 'torchmetrics'}))\n"
        "from ssm_ms.inference import FilterForecaster, UnscentedKalmanFilter, fit_nodes\n"
        "print(UnscentedKalmanFilter is ssm_ms.inference.ukf.UnscentedKalmanFilter, FilterForecaster.__module__)\n"
        "print([getattr(ssm_ms.inference, name).__name__ for name in ssm_ms.inference.__all__])"
    )
    out = subprocess.run([sys.executable, "-c", script], cwd=ROOT, capture_output=True, text=True, check=True)
    lines = out.stdout.splitlines()
    assert lines[:2] == ["[]", "True ssm_ms.inference.filter_module"], out.stdout + out.stderr
    assert "'fit_nodes'" in lines[2] and "'StateEncoderModule'" in lines[2], lines[2]


# The layers of ssm_ms, lowest first: a module imports only modules of its own layer or lower ones (and never the
# data sets: the CLI builds data and model from the config's class paths).
LAYERS = {
    0: (
        "ssm_ms.runtime",
        "ssm_ms.training",
        "ssm_ms.nets",
        "ssm_ms.checkpointing",
        "ssm_ms.drawing",
        "ssm_ms.units",
        "ssm_ms.arrays",
    ),
    1: (
        "ssm_ms.module",
        "ssm_ms.loading",
        "ssm_ms.schedule",
        "ssm_ms.averaging",
        "ssm_ms.progress",
        "ssm_ms.viz",
        "ssm_ms.analysis",
        "ssm_ms.export",
    ),
    2: ("ssm_ms.inference", "ssm_ms.forecasting", "ssm_ms.baselines", "ssm_ms.control"),
    3: ("ssm_ms.cli", "ssm_ms.pretrained", "ssm_ms.api", "ssm_ms.trainer", "ssm_ms.__main__"),
}


def layer(module: str) -> int | None:
    for rank, prefixes in LAYERS.items():
        if any(module == p or module.startswith(p + ".") for p in prefixes):
            return rank
    return 3 if module == "ssm_ms" else None  # the package's names are the Python API's (lazily imported)


def test_every_module_has_a_layer():
    unplaced = sorted(m for m in method_graph() if layer(m) is None)
    assert unplaced == [], f"modules in no layer of LAYERS (place them; docs/layout.md names the layers): {unplaced}"


def test_no_module_imports_a_higher_layer():
    graph = method_graph()
    upward = sorted(f"{m} -> {d}" for m, deps in graph.items() for d in deps if layer(d) > layer(m))
    assert upward == [], f"imports against the layers (lower layers must not know higher ones): {upward}"


# the one module of ssm_ms that builds data: the Python API's Recordings (arrays in memory); the CLI builds data and
# model from the config's class paths
BUILDS_DATA = ("ssm_ms/api.py",)


def test_the_method_never_imports_the_data_sets():
    for path in sorted((ROOT / "ssm_ms").rglob("*.py")):
        data = sorted(m for m in imported_modules(path) if m == "datamodules" or m.startswith("datamodules."))
        if str(path.relative_to(ROOT)) in BUILDS_DATA:
            assert data, f"{path.relative_to(ROOT)} imports no data set: drop it from BUILDS_DATA"
            continue
        assert not data, (
            f"{path.relative_to(ROOT)} imports {data}: the data set passes what it knows in (e.g. dm.wing_level())"
        )


def test_the_layer_check_sees_an_upward_import(monkeypatch):
    fake = {"ssm_ms.training.shooting": {"ssm_ms.module"}, "ssm_ms.module": set()}
    monkeypatch.setitem(globals(), "method_graph", lambda: fake)
    import pytest

    with pytest.raises(AssertionError, match="ssm_ms.training.shooting -> ssm_ms.module"):
        test_no_module_imports_a_higher_layer()


# The application (experiments/: the registry's experiments, make reproduce, the reports and README tables) is the
# layer above the method and the data: it may import both; neither imports it.
def application_modules() -> dict[str, Path]:
    files = {}
    for p in (ROOT / "experiments").rglob("*.py"):
        parts = p.relative_to(ROOT).with_suffix("").parts
        files[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = p
    return files


def test_neither_the_method_nor_the_data_import_the_application():
    files = sorted((ROOT / "ssm_ms").rglob("*.py")) + sorted((ROOT / "datamodules").rglob("*.py"))
    upward = {
        str(p.relative_to(ROOT)): sorted(m for m in imported_modules(p) if m.split(".")[0] == "experiments")
        for p in files
    }
    assert {k: v for k, v in upward.items() if v} == {}, "the library imports the application (experiments/)"


def test_the_application_imports_without_a_circle():
    files = application_modules()
    assert {"experiments.reproduce", "experiments.results", "experiments.readme", "experiments.cli"} <= set(files)
    graph = {
        name: {d for d in imported_modules(path) if d in files and d != name and not name.startswith(d + ".")}
        for name, path in files.items()
    }
    assert "experiments.results" in graph["experiments.readme"]  # the graph is read
    assert_no_circle(graph)
