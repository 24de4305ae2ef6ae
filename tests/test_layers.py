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
    "settings": ("dswm.protocol", "dswm.pipeline", "dswm.figures"),
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


SHARED_METHOD_MODULES = {
    # the shared layer of dswm.methods: every method may import these; they import no method
    "dswm.methods", "dswm.methods.base", "dswm.methods.registry", "dswm.methods.trained", "dswm.methods.search",
    "dswm.methods.snapshots", "dswm.methods.collect", "dswm.methods.replay", "dswm.methods.matmul",
    # the classical baselines double as building blocks: BatchedController (INS-WOA), the greedy pre-collection
    "dswm.methods.classical",
    # the RL infrastructure; its one method module, dswm.methods.rl.sb3 (ppo, sac), is not shared
    "dswm.methods.rl", "dswm.methods.rl.spaces", "dswm.methods.rl.vec_env", "dswm.methods.rl.logger",
    "dswm.methods.rl.common", "dswm.methods.rl.sac_train",
}


def method_unit(name: str) -> str | None:
    """The method package or module that the dotted ``name`` lies in (``dswm.methods.tdmpc`` for everything under
    it; each module of ``dswm.methods.rl`` is its own); None for the shared layer and for anything outside."""
    parts = name.split(".")
    if parts[:2] != ["dswm", "methods"] or len(parts) < 3:
        return None
    unit = ".".join(parts[:4] if parts[2] == "rl" and len(parts) > 3 else parts[:3])
    return None if unit in SHARED_METHOD_MODULES else unit


def method_violations(src: Path = SRC) -> list[str]:
    """Every import by a module of ``src/methods`` of another method's package or module (a shared module may
    import the shared layer only)."""
    bad = []
    for path in sorted((src / "methods").rglob("*.py")):
        rel = path.relative_to(src.parent).with_suffix("")
        own = method_unit(".".join(rel.parts[:-1] if rel.name == "__init__" else rel.parts))
        for line, module, names in imports_of(path):
            units = {method_unit(t) for t in [module] + [f"{module}.{n}" for n in names]} - {None, own}
            if units:
                bad.append(f"{path.relative_to(src.parent).as_posix()}:{line} imports {sorted(units)[0]}")
    return bad


def test_no_method_imports_another_method():
    assert method_violations() == []


def test_the_check_sees_a_method_importing_another(tmp_path):
    """The test above can fail: a method importing another's module, and a shared module importing a method."""
    for pkg in ("tdmpc", "dswm", "rl"):
        (tmp_path / "dswm" / "methods" / pkg).mkdir(parents=True)
    (tmp_path / "dswm" / "methods" / "tdmpc" / "agent.py").write_text(
        "from dswm.methods.collect import collect\nfrom dswm.methods.tdmpc.model import TOLD\n\n\ndef f():\n"
        "    from dswm.methods.dswm.training import train\n")
    (tmp_path / "dswm" / "methods" / "tdmpc" / "replay.py").write_text("from dswm.methods import dswm\n")
    (tmp_path / "dswm" / "methods" / "rl" / "common.py").write_text("from dswm.methods.rl.sb3 import PPOSettings\n")
    (tmp_path / "dswm" / "methods" / "trained.py").write_text("from dswm.methods.maddpg.learner import Learner\n")
    assert method_violations(tmp_path / "dswm") == [
        "dswm/methods/rl/common.py:1 imports dswm.methods.rl.sb3",
        "dswm/methods/tdmpc/agent.py:6 imports dswm.methods.dswm",
        "dswm/methods/tdmpc/replay.py:1 imports dswm.methods.dswm",
        "dswm/methods/trained.py:1 imports dswm.methods.maddpg"]


def prep_violations(src: Path = ROOT / "src") -> list[str]:
    """Every import of ``dswm`` in ``src/prep`` (the data preparation sits below the package)."""
    return [f"{path.relative_to(src).as_posix()}:{line} imports {module}"
            for path in sorted((src / "prep").rglob("*.py")) for line, module, _ in imports_of(path)
            if module == "dswm" or module.startswith("dswm.")]


def test_prep_imports_nothing_of_dswm(tmp_path):
    assert prep_violations() == []
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "bad.py").write_text("import os\n\n\ndef f():\n    from dswm.config import ConfigError\n")
    (tmp_path / "prep" / "worse.py").write_text("from dswm import config\n")
    assert prep_violations(tmp_path) == ["prep/bad.py:5 imports dswm.config", "prep/worse.py:1 imports dswm"]


def test_a_handful_of_modules_sit_directly_in_the_package():
    top = sorted(p.name for p in SRC.glob("*.py") if p.name != "__init__.py")
    assert len(top) <= 4, top
    assert {p.name for p in SRC.iterdir() if p.is_dir() and (p / "__init__.py").exists()} == \
        {"sim", "methods", "protocol", "pipeline", "settings", "figures"}


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
    assert defined == ["src/prep/typed.py"]      # below prep and dswm; dswm.config hands it to every dswm module
    readers = [p.name for p in (ROOT / "workflow" / "scripts").glob("*.py") if "snakemake.config" in p.read_text()]
    assert readers == []


def prep_import_cycles(src: Path = ROOT / "src") -> list[list[str]]:
    """Every cycle of the import graph of ``src/prep`` (function-level imports included), each as the modules it
    passes through, starting from its smallest name."""
    modules = {".".join(p.relative_to(src).with_suffix("").parts).removesuffix(".__init__"): p
               for p in sorted((src / "prep").rglob("*.py"))}
    graph = {m: sorted({t for _, module, names in imports_of(p) for t in [module] + [f"{module}.{n}" for n in names]
                        if t in modules and t != m}) for m, p in modules.items()}
    cycles = set()

    def walk(node, path):
        for nxt in graph[node]:
            if nxt in path:
                cycle = path[path.index(nxt):]
                i = cycle.index(min(cycle))
                cycles.add(tuple(cycle[i:] + cycle[:i]))
            elif len(path) < len(graph):
                walk(nxt, path + [nxt])

    for start in graph:
        walk(start, [start])
    return sorted(map(list, cycles))


def test_prep_has_no_import_cycle(tmp_path):
    """prep.config builds the sections that prep.days checks; the shared dataclasses sit below both
    (prep.sections), so neither module needs the other's lazily."""
    assert prep_import_cycles() == []
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "config.py").write_text("from prep.days import check_days\n")
    (tmp_path / "prep" / "days.py").write_text("def f():\n    from prep.config import Split\n")
    assert prep_import_cycles(tmp_path) == [["prep.config", "prep.days"]]


def private_imports(src: Path = ROOT / "src") -> list[str]:
    """Every import by a module of ``src`` of a private name (``_x``) of a project module (dswm, prep)."""
    bad = []
    for path in sorted(src.rglob("*.py")):
        for line, module, names in imports_of(path):
            if module.split(".")[0] in ("dswm", "prep"):
                bad += [f"{path.relative_to(src).as_posix()}:{line} {module}.{n}" for n in names if n.startswith("_")]
    return bad


def test_no_module_imports_another_modules_private_names(tmp_path):
    assert private_imports() == []
    (tmp_path / "dswm" / "pipeline").mkdir(parents=True)
    (tmp_path / "dswm" / "pipeline" / "probe.py").write_text(
        "from dswm.pipeline.setup import set_up\n\n\ndef f():\n"
        "    from dswm.pipeline.jobs import DAY_METRICS, _common\n")
    assert private_imports(tmp_path) == ["dswm/pipeline/probe.py:5 dswm.pipeline.jobs._common"]


MAX_MODULE_LINES = 400
"""The longest a module of ``src`` may be."""


def long_modules(src: Path = ROOT / "src") -> list[str]:
    """The modules of ``src`` over :data:`MAX_MODULE_LINES` lines, with their length."""
    return [f"{p.relative_to(src).as_posix()}: {n}" for p in sorted(src.rglob("*.py"))
            if (n := len(p.read_text().splitlines())) > MAX_MODULE_LINES]


def test_no_module_over_400_lines_and_no_mid_file_import(tmp_path):
    assert long_modules() == []
    assert [f"{p.relative_to(ROOT)}" for p in (ROOT / "src").rglob("*.py") if "noqa: E402" in p.read_text()] == []
    (tmp_path / "prep").mkdir()
    (tmp_path / "prep" / "long.py").write_text("x = 1\n" * 401)
    (tmp_path / "prep" / "short.py").write_text("x = 1\n" * 400)
    assert long_modules(tmp_path) == ["prep/long.py: 401"]
