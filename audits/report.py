"""Check results and the audit report (results/audit/report.json and report.md).

Every check has an id (`family.name`), a one-line statement of what it proves, a verdict, the evidence
(numbers recomputed by the audit next to the stored ones) and, when it fails, one message per finding that
names the file and the leak.
"""
from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from prep.atomic import write_text

FAMILIES = ("splits", "statistics", "protocol", "read-only")


@dataclass(kw_only=True)
class Check:
    """One check's verdict.

    Attributes:
        id: "family.name", e.g. "splits.segments".
        family: one of FAMILIES.
        claim: what a pass proves, one sentence.
        failures: one message per finding ("<file>: <what leaks>"); empty = pass.
        evidence: recomputed and stored values, per dataset or file.
        tolerance: how close recomputed and stored values must be, in words ("" when exact).
    """

    id: str
    family: str
    claim: str
    failures: list[str] = field(default_factory=list)
    evidence: dict[str, Any] = field(default_factory=dict)
    tolerance: str = ""

    @property
    def passed(self) -> bool:
        return not self.failures

    def fail(self, message: str) -> None:
        """Records a finding (the message names the file and the leak)."""
        self.failures.append(message)

    def to_dict(self) -> dict:
        return {**asdict(self), "passed": self.passed}


def write_atomic(path: Path, text: str) -> None:
    """Writes text to a temp file beside `path`, then renames it into place."""
    write_text(path, text)


def _jsonable(obj: Any) -> Any:
    """Numpy scalars and arrays, paths and tuples turned into plain JSON values."""
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, Path):
        return str(obj)
    if hasattr(obj, "tolist"):
        return obj.tolist()
    return obj


def build_report(*, checks: list[Check], read_only: dict, header: dict) -> dict:
    """The report as a JSON-able dict: header, per-family verdicts, checks, read-only proof."""
    families = {f: {"passed": all(c.passed for c in checks if c.family == f),
                    "checks": [c.id for c in checks if c.family == f]} for f in FAMILIES}
    return _jsonable({**header, "passed": all(c.passed for c in checks),
                      "families": families, "checks": [c.to_dict() for c in checks], "read_only": read_only})


def _short(value: Any, limit: int = 160) -> str:
    text = json.dumps(_jsonable(value), sort_keys=True)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def to_markdown(report: dict) -> str:
    """Human-readable report: verdict table, failures first, then the evidence of every check."""
    ok = "PASS" if report["passed"] else "FAIL"
    lines = [f"# Leakage audit: {ok}", "",
             f"Profile `{report['profile']}`, scope `{report.get('scope', 'all')}`, datasets "
             f"{', '.join(report['datasets'])}, methods "
             f"{', '.join(report['methods'])}. Files read: {len(report['read_only']['files'])}, "
             f"changed by the audit: {len(report['read_only']['changed'])}.", "",
             "| family | check | verdict | claim |", "|---|---|---|---|"]
    for c in report["checks"]:
        lines.append(f"| {c['family']} | `{c['id']}` | {'pass' if c['passed'] else '**FAIL**'} | {c['claim']} |")
    failing = [c for c in report["checks"] if not c["passed"]]
    if failing:
        lines += ["", "## Findings", ""]
        for c in failing:
            lines += [f"### `{c['id']}`", ""] + [f"- {m}" for m in c["failures"]] + [""]
    lines += ["", "## Evidence", ""]
    for c in report["checks"]:
        lines += [f"### `{c['id']}` — {'pass' if c['passed'] else 'FAIL'}", "", c["claim"], ""]
        if c["tolerance"]:
            lines += [f"Tolerance: {c['tolerance']}", ""]
        for key, value in c["evidence"].items():
            lines.append(f"- `{key}`: {_short(value)}")
        lines.append("")
    ro = report["read_only"]
    lines += ["## Read-only proof", "",
              f"{len(ro['files'])} files hashed (SHA-256) before their first read and again at the end; "
              f"{'none changed' if not ro['changed'] else 'CHANGED: ' + ', '.join(ro['changed'])}; "
              f"write-mode opens refused: {len(ro['write_attempts'])}.", "",
              "| file | sha256 | unchanged |", "|---|---|---|"]
    for f in ro["files"]:
        lines.append(f"| `{f['path']}` | `{f['sha256_before'][:16]}` | {'yes' if f['unchanged'] else 'NO'} |")
    return "\n".join(lines) + "\n"


def write_report(report: dict, *, json_path: Path, md_path: Path) -> None:
    """Writes report.json and report.md atomically."""
    write_atomic(Path(json_path), json.dumps(report, indent=2, sort_keys=True) + "\n")
    write_atomic(Path(md_path), to_markdown(report))
