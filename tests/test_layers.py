"""The package's layers, read from the source with ``ast``: imports go downward only, one way to each name."""
import ast
from pathlib import Path

import pytest

from conftest import ROOT

SRC = ROOT / "src" / "dswm"
FORBIDDEN = {
    # layer: the packages it must not import (the layers above it)
    "sim": ("dswm.methods", "dswm.protocol", "dswm.pipeline", "dswm.settings", "dswm.figures"),
    "methods": ("dswm.protocol", "dswm.pipeline", "dswm.settings", "dswm.figures"),
    "protocol": ("dswm.pipeline", "dswm.settings", "dswm.figures"),
    "pipeline": ("dswm.figures",),
    # the figures draw from result files only: no simulator, no method
    "figures": ("dswm.sim", "dswm.methods"),
}


def imports_of(path: Path) -> list[tuple[int, str, list[str]]]:
    """(line, module, imported names) of every import in ``path``, function-level imports included."""
    out = []
    for node in ast.walk(ast.parse(path.read_text(), filename=str(path))):
        if isinstance(node, ast.Import):
            out += [(node.lineno, a.name, []) for a in node.names]
        elif isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
            out.append((node.lineno, node.module, [a.name for a in node.names]))
    return out


def violations(layer: str, src: Path = SRC) -> list[str]:
    """Every import in ``src/<layer>`` of a package above it (``from dswm import settings`` included)."""
    bad = []
    for path in sorted((src / layer).rglob("*.py")):
        for line, module, names in imports_of(path):
            targets = [module] + [f"{module}.{n}" for n in names]
            hit = [t for t in targets for above in FORBIDDEN[layer] if t == above or t.startswith(above + ".")]
            if hit:
                bad.append(f"{path.relative_to(src.parent).as_posix()}:{line} imports {hit[0]}")
    return bad


@pytest.mark.parametrize("layer", sorted(FORBIDDEN))
def test_imports_go_downward_only(layer):
    assert violations(layer) == []


def test_the_check_sees_an_upward_import(tmp_path):
    """The test above can fail: upward imports, inside a function or through the package, are reported."""
    (tmp_path / "dswm" / "sim").mkdir(parents=True)
    (tmp_path / "dswm" / "sim" / "bad.py").write_text(
        "import torch\nfrom dswm.sim import core\n\n\ndef f():\n    from dswm.protocol.evaluation import evaluate\n")
    (tmp_path / "dswm" / "sim" / "worse.py").write_text("from dswm import settings\n")
    assert violations("sim", tmp_path / "dswm") == ["dswm/sim/bad.py:6 imports dswm.protocol.evaluation",
                                                     "dswm/sim/worse.py:1 imports dswm.settings"]


def test_a_handful_of_modules_sit_directly_in_the_package():
    top = sorted(p.name for p in SRC.glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 4, top
    assert {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()} == \
        {"sim", "methods", "protocol", "pipeline", "figures"}


def test_each_name_of_the_simulator_has_one_import_path():
    """The environment views do not re-export the core: its names are imported from dswm.sim.core only."""
    env_own = {n.name for n in ast.parse((SRC / "sim" / "env.py").read_text()).body
               if isinstance(n, (ast.ClassDef, ast.FunctionDef))} | {"ENV_ID"}
    bad = []
    for path in [*ROOT.glob("src/**/*.py"), *ROOT.glob("tests/*.py"), *ROOT.glob("audits/*.py"),
                 *ROOT.glob("benchmarks/*.py"), *ROOT.glob("workflow/scripts/*.py")]:
        for line, module, names in imports_of(path):
            if module == "dswm.sim.env":
                bad += [f"{path.relative_to(ROOT)}:{line} {n}" for n in names if n not in env_own]
    assert bad == []


def test_one_config_error_and_no_script_reads_the_whole_config():
    defined = [f"{p.relative_to(ROOT)}" for p in [*ROOT.glob("src/**/*.py"), *ROOT.glob("audits/*.py")]
               for node in ast.walk(ast.parse(p.read_text())) if isinstance(node, ast.ClassDef)
               and node.name == "ConfigError"]
    assert defined == ["src/dswm/config.py"]
    readers = [p.name for p in (ROOT / "workflow" / "scripts").glob("*.py") if "snakemake.config" in p.read_text()]
    assert readers == []
