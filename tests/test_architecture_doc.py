"""docs/ARCHITECTURE.md names code; every name it gives as code must exist, so the page cannot drift silently.

The page states its convention at the top ("Names in this page"): a dotted name in backticks or in a code block
that starts with ``dswm``, ``prep`` or ``audits`` is a full path; in a section whose heading names a module in
backticks, a code-block line that starts (in its first column) with ``name(`` or ``a.b(`` names something of
that module, as does every further ``name(`` on that line after two spaces or ``; `` (before a ``  #`` comment).
Each such name is imported: the longest importable module prefix, then attributes.
"""
import importlib
import inspect
import re
import sys

import pytest

from conftest import ROOT

DOC = ROOT / "docs" / "ARCHITECTURE.md"
PACKAGES = ("dswm", "prep", "audits")
DOTTED = r"[A-Za-z_]\w*(?:\.[A-Za-z_]\w*)*"


def _is_absolute(name: str) -> bool:
    return name.split(".", 1)[0] in PACKAGES


def doc_names(text: str) -> dict[str, int]:
    """{dotted name: first line} of every name the page gives as code, by the convention above."""
    names: dict[str, int] = {}
    base, in_block = None, False
    for number, line in enumerate(text.splitlines(), 1):
        if line.startswith("```"):
            in_block = not in_block
            continue
        if not in_block and line.startswith("#"):
            heading = re.search(r"`(" + DOTTED + r")`", line)
            base = heading.group(1) if heading and _is_absolute(heading.group(1)) else None
            continue
        if in_block:
            found = [m.group(1) for m in re.finditer(r"(?<![\w./<-])(" + DOTTED + r")", line)]
            found = [n for n in found if "." in n and _is_absolute(n)]
            if base and re.match(DOTTED + r"\(", line):           # a line that starts with a call form
                code = line.split("  #", 1)[0]
                calls = re.findall(r"(?:^|  |; )(" + DOTTED + r")\(", code)
                found += [f"{base}.{n}" for n in calls if not _is_absolute(n)]
        else:
            found = [n for n in re.findall(r"`(" + DOTTED + r")`", line) if _is_absolute(n)]
        for name in found:
            names.setdefault(name, number)
    return names


def _home(obj, attr: str, module: str) -> bool:
    """``obj`` (``module``'s ``attr``) is defined in ``module`` or below it (a package's own submodule), or
    ``module`` declares it in ``__all__``."""
    return obj.__module__ == module or obj.__module__.startswith(module + ".") \
        or attr in getattr(sys.modules[module], "__all__", ())


def resolves(name: str) -> bool:
    """True when ``name`` is a module, or attributes of the longest importable module prefix of it; a class or
    function named right under a module must be defined there or in a submodule of that package, or be one of its
    declared names (``__all__``): a module that merely imports it from elsewhere is not where the page may place it."""
    parts = name.split(".")
    for cut in range(len(parts), 0, -1):
        module = ".".join(parts[:cut])
        try:
            obj = importlib.import_module(module)
        except ImportError:
            continue
        try:
            for i, attr in enumerate(parts[cut:]):
                obj = getattr(obj, attr)
                if i == 0 and (inspect.isclass(obj) or inspect.isfunction(obj)) and not _home(obj, attr, module):
                    return False
        except AttributeError:
            return False
        return True
    return False


def test_every_name_the_architecture_page_gives_as_code_exists():
    names = doc_names(DOC.read_text())
    assert len(names) > 100                       # the page names the code throughout
    missing = [f"{name} (line {line})" for name, line in names.items() if not resolves(name)]
    assert missing == [], f"docs/ARCHITECTURE.md names code that does not exist: {missing}"


def test_the_page_states_the_convention():
    head = DOC.read_text().split("\n## ", 1)[0]
    assert "tests/test_architecture_doc.py" in head and "Names in this page" in head


@pytest.mark.parametrize("name, exists", [("dswm.sim.physics.served_ratio", True), ("dswm.sim.physics", True),
                                          ("dswm.sim.physics.no_such_name", False), ("dswm.no_such_module", False),
                                          ("prep.atomic.write_json", True),
                                          ("dswm.methods.dswm.agent.Controller", False)])    # imported there only
def test_the_check_resolves_names(name, exists):
    assert resolves(name) is exists


def test_the_reader_follows_the_convention():
    text = "\n".join([
        "# Title", "Prose with `dswm.sim.physics` and `Controller.fit` (relative in prose: not read).",
        "## Pipeline (`dswm.pipeline`)", "```", "jobs.train_job(*, job) -> manifest; jobs.f(x)  # not_read(y)",
        "    continued(x)        # an indented line: not a name", "tracking.init_store(*, store)  see prep.tensor.load",
        "```", "## Other", "```", "free(x) -> y", "```"])
    assert doc_names(text) == {"dswm.sim.physics": 2, "dswm.pipeline.jobs.train_job": 5, "dswm.pipeline.jobs.f": 5,
                               "dswm.pipeline.tracking.init_store": 7, "prep.tensor.load": 7}


def test_a_package_may_present_the_names_of_its_submodules(tmp_path, monkeypatch):
    """A package that re-exports what its submodules define (``dswm.settings`` as a package) passes; a module that
    imports a name from a sibling does not become its home."""
    pkg = tmp_path / "docpkg"
    (pkg / "inner").mkdir(parents=True)
    (pkg / "__init__.py").write_text("")
    (pkg / "base.py").write_text("def helper():\n    pass\n")
    (pkg / "user.py").write_text("from docpkg.base import helper\n")
    (pkg / "inner" / "__init__.py").write_text("from docpkg.inner.part import resolve\n")
    (pkg / "inner" / "part.py").write_text("def resolve():\n    pass\n")
    monkeypatch.syspath_prepend(str(tmp_path))
    assert resolves("docpkg.base.helper") and resolves("docpkg.inner.resolve")
    assert not resolves("docpkg.user.helper")
