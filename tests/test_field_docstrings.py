"""Every field of the settings dataclasses of the data preparation and the scenario says what it is, in an
attribute docstring under it (the house's habit: a typed dataclass, each field with a one-line docstring)."""
import ast
from pathlib import Path

import pytest

from conftest import ROOT

DOCUMENTED = ["src/prep/config.py", "src/prep/sections.py", "src/dswm/sim/scenario.py"]


def undocumented_fields(path: Path) -> list[str]:
    """``Class.field`` of every dataclass field in ``path`` without a string literal right under it."""
    missing = []
    for node in ast.walk(ast.parse(path.read_text())):
        if not isinstance(node, ast.ClassDef):
            continue
        decorators = [ast.unparse(d) for d in node.decorator_list]
        if not any(d.split("(")[0].endswith("dataclass") for d in decorators):
            continue
        for item, after in zip(node.body, node.body[1:] + [None]):
            if isinstance(item, ast.AnnAssign) and isinstance(item.target, ast.Name):
                doc = isinstance(after, ast.Expr) and isinstance(after.value, ast.Constant) \
                    and isinstance(after.value.value, str) and after.value.value.strip()
                if not doc:
                    missing.append(f"{node.name}.{item.target.id}")
    return missing


@pytest.mark.parametrize("module", DOCUMENTED)
def test_every_field_has_a_docstring(module):
    assert undocumented_fields(ROOT / module) == []


def test_the_check_sees_a_field_without_a_docstring(tmp_path):
    src = tmp_path / "m.py"
    src.write_text('import dataclasses\n\n\n@dataclasses.dataclass(frozen=True)\nclass A:\n    """A."""\n\n'
                   '    x: int\n    """The x."""\n    y: int  # a comment is not a docstring\n    z: int\n\n\n'
                   'class Plain:\n    w: int\n')
    assert undocumented_fields(src) == ["A.y", "A.z"]
