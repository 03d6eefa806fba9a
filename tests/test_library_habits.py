"""Library habits: errors are ValueErrors that keep their cause, no hidden process-wide state, bounded caches,
dependencies that point one way (no import cycle), function-local imports only with a stated reason, and a
command line whose ``--help`` starts without torch."""

import ast
import io
import os
import re
import subprocess
import sys
import tokenize
from pathlib import Path

import pytest
import torch

import d2turb
import d2turb.eval.musiq as musiq_module
from d2turb.errors import D2TurbError
from d2turb.io import read_image
from d2turb.sim import TurbulenceParams
from d2turb.sim.psf import pca_basis


def test_d2turb_error_is_a_value_error_that_keeps_its_cause(tmp_path):
    assert issubclass(D2TurbError, ValueError)
    with pytest.raises(ValueError, match="aperture_m must be a number") as err:
        TurbulenceParams(aperture_m="wide")
    assert isinstance(err.value.__cause__, ValueError)  # float("wide")
    bad = tmp_path / "bad.png"
    bad.write_bytes(b"\x89PNG\r\n\x1a\nnot really")
    with pytest.raises(D2TurbError, match="cannot read image") as err:
        read_image(bad)
    assert err.value.__cause__ is not None


def test_pca_basis_leaves_the_thread_count_as_it_found_it():
    torch.set_num_threads(2)
    psfs = torch.rand(50, 9, 9, generator=torch.Generator().manual_seed(0))
    pca_basis(psfs / psfs.sum(dim=(-2, -1), keepdim=True))
    assert torch.get_num_threads() == 2


def test_depth_anything_does_not_set_hf_hub_offline(tmp_path, monkeypatch):
    pytest.importorskip("transformers")
    from d2turb.depth import DepthAnything

    monkeypatch.delenv("HF_HUB_OFFLINE", raising=False)
    (tmp_path / "config.json").write_text("{}")  # a folder that exists but holds no model
    with pytest.raises(D2TurbError, match="cannot load"):
        DepthAnything(tmp_path)
    assert "HF_HUB_OFFLINE" not in os.environ


@pytest.fixture
def fake_musiq(monkeypatch):
    """MUSIQ replaced by a counter of loads; the model cache is emptied before and after."""
    loads = []

    class Fake:
        def __init__(self, path, device="cpu"):
            loads.append(path.name)

        def __call__(self, image):
            return torch.zeros(image.shape[0])

    musiq_module._cached_model.cache_clear()
    monkeypatch.setattr(musiq_module, "MUSIQ", Fake)
    yield loads
    musiq_module._cached_model.cache_clear()


def test_musiq_model_cache_is_bounded(tmp_path, fake_musiq):
    files = []
    for name in "abc":
        files.append(tmp_path / f"{name}.pth")
        files[-1].write_bytes(b"")
    image = torch.rand(1, 3, 8, 8)
    for path in files + files[-1:]:  # a, b, c, then c again: cached
        musiq_module.musiq(image, weights=path)
    assert fake_musiq == ["a.pth", "b.pth", "c.pth"]
    musiq_module.musiq(image, weights=files[0])  # a was evicted: at most two models stay loaded
    assert fake_musiq == ["a.pth", "b.pth", "c.pth", "a.pth"]
    assert musiq_module._cached_model.cache_info().currsize == 2


# ---- imports: read with ast from the installed package's sources ---------------------------------------------------
PACKAGE = Path(d2turb.__file__).parent


def _modules() -> dict[str, Path]:
    """Dotted module name → source file, for every module of the package (a package is its __init__.py)."""
    out = {}
    for path in PACKAGE.rglob("*.py"):
        parts = (PACKAGE.name, *path.relative_to(PACKAGE).with_suffix("").parts)
        out[".".join(parts[:-1] if parts[-1] == "__init__" else parts)] = path
    return out


MODULES = _modules()


def _imported(module: str, node: ast.Import | ast.ImportFrom) -> list[str]:
    """The project modules an import statement in ``module`` names (``from a.b import c``: a.b, and a.b.c if it is a
    module); the packages above them are added by the caller."""
    if isinstance(node, ast.Import):
        return [a.name for a in node.names]
    base = node.module or ""
    if node.level:  # relative: from the package that holds ``module``
        package = module.split(".") if MODULES[module].name == "__init__.py" else module.split(".")[:-1]
        base = ".".join(package[: len(package) - node.level + 1] + ([node.module] if node.module else []))
    return [base] + [f"{base}.{a.name}" for a in node.names if f"{base}.{a.name}" in MODULES]


def _is_type_checking(node: ast.AST) -> bool:
    return isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test)


def _import_graph() -> dict[str, set[str]]:
    """Module → the project modules its module-level code imports (function bodies and ``if TYPE_CHECKING:`` blocks
    excluded). Importing ``a.b.c`` also runs the packages ``a`` and ``a.b``, except the importer's own packages,
    which are already initialised (or initialising) when it runs."""
    graph = {}
    for module, path in MODULES.items():
        targets = set()
        stack = list(ast.parse(path.read_text()).body)
        while stack:
            node = stack.pop()
            if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda)) or _is_type_checking(node):
                continue
            if isinstance(node, (ast.Import, ast.ImportFrom)):
                for name in _imported(module, node):
                    parts = name.split(".")
                    targets.update(".".join(parts[:i]) for i in range(1, len(parts) + 1))
                continue
            stack.extend(ast.iter_child_nodes(node))
        own = {".".join(module.split(".")[:i]) for i in range(1, module.count(".") + 2)}
        graph[module] = {t for t in targets if t in MODULES and t not in own}
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """Strongly connected components with more than one module (Tarjan), each sorted."""
    index, low, stack, on_stack, found = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


PRAGMA = re.compile(r"#\s*(noqa|type:|pragma:|fmt:)")  # tool directives, not reasons


def _unreasoned_local_imports(module: str) -> list[str]:
    """``file:line: statement`` for each project import inside a function of ``module`` without a stated reason:
    a comment on the statement's own lines (a ``noqa``-style directive is no reason), or a comment line directly
    above the first of the consecutive import statements it belongs to (one comment covers an import block)."""
    path = MODULES[module]
    text = path.read_text()
    lines = text.splitlines()
    tokens = tokenize.generate_tokens(io.StringIO(text).readline)
    commented = {t.start[0] for t in tokens if t.type == tokenize.COMMENT and not PRAGMA.match(t.string)}
    missing = []

    def check(node, in_function):
        for field in ("body", "orelse", "finalbody", "handlers"):
            block = getattr(node, field, None)
            if not isinstance(block, list):
                continue
            run_start = None  # first statement of the current run of consecutive imports
            for stmt in block:
                if not isinstance(stmt, (ast.Import, ast.ImportFrom)):
                    run_start = None
                    continue
                run_start = run_start or stmt
                project = getattr(stmt, "level", 0) or any(
                    n.split(".")[0] == PACKAGE.name for n in _imported(module, stmt)
                )
                if not (in_function and project):
                    continue
                own = commented & set(range(stmt.lineno, stmt.end_lineno + 1))
                above = run_start.lineno - 1
                if not own and not (above in commented and lines[above - 1].lstrip().startswith("#")):
                    missing.append(f"{path.relative_to(PACKAGE.parent)}:{stmt.lineno}: {ast.unparse(stmt)}")
        for child in ast.iter_child_nodes(node):
            if not _is_type_checking(child):
                check(child, in_function or isinstance(child, (ast.FunctionDef, ast.AsyncFunctionDef)))

    check(ast.parse(text), False)
    return missing


def test_no_import_cycle_among_module_level_project_imports():
    graph = _import_graph()
    assert "d2turb.depth.io" in graph["d2turb.depth.anything"]  # the graph sees real edges
    assert _cycles(graph) == []


def test_model_registry_knows_no_concrete_model():
    graph = _import_graph()
    assert not {m for m in graph["d2turb.models.registry"] if m.startswith("d2turb.models.")}
    tree = ast.parse(MODULES["d2turb.models.registry"].read_text())
    named = {
        n
        for node in ast.walk(tree)
        if isinstance(node, (ast.Import, ast.ImportFrom))
        for n in _imported("d2turb.models.registry", node)
    }
    assert not {n for n in named if n.startswith("d2turb.models.")}, "the registry imports a model module"


def test_function_local_project_imports_state_a_reason():
    assert [line for module in sorted(MODULES) for line in _unreasoned_local_imports(module)] == []


def test_cli_and_its_help_start_without_torch():
    code = (
        "import contextlib, io, sys\n"
        "import d2turb.cli\n"
        "assert 'torch' not in sys.modules, 'import d2turb.cli imported torch'\n"
        "with contextlib.redirect_stdout(io.StringIO()) as out:\n"
        "    rc = d2turb.cli.main(['--help'])\n"
        "assert rc == 0 and 'simulate' in out.getvalue(), out.getvalue()\n"
        "heavy = sorted(m for m in ('torch', 'numpy', 'scipy', 'PIL') if m in sys.modules)\n"
        "assert not heavy, f'd2turb --help imported {heavy}'\n"
    )
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(PACKAGE.parent), os.environ.get("PYTHONPATH", "")])}
    done = subprocess.run([sys.executable, "-c", code], env=env, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
