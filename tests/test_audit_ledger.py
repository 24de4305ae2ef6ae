"""The audit's read-only proof (ledger, write guard) and its pass/fail gate."""
from __future__ import annotations

import hashlib
import json
import os

import pytest

from audits.ledger import ReadLedger, ReadOnlyViolation
from audits.report import Check, build_report, write_report
from audits.runner import gate


@pytest.fixture
def audited(tmp_path):
    root = tmp_path / "root"
    (root / "results").mkdir(parents=True)
    f = root / "results" / "meta.json"
    f.write_text('{"p99": 1.5}')
    return root, f, ReadLedger(root=root, guarded=[root])


def test_tracked_files_are_hashed_before_reading(audited):
    root, f, ledger = audited
    assert ledger.read_json(f) == {"p99": 1.5}
    proof = ledger.verify()
    assert proof["unchanged"] and proof["changed"] == []
    row = proof["files"][0]
    assert row["path"] == "results/meta.json"
    assert row["sha256_before"] == row["sha256_after"] == hashlib.sha256(b'{"p99": 1.5}').hexdigest()


def test_a_changed_or_touched_file_is_reported(audited):
    root, f, ledger = audited
    g = root / "results" / "days.parquet"
    g.write_bytes(b"rows")
    ledger.track(f)
    ledger.track(g)
    f.write_text('{"p99": 9.9}')  # content changed after the first read
    st = g.stat()
    os.utime(g, ns=(st.st_atime_ns, st.st_mtime_ns + 10**9))  # same bytes, new modification time
    proof = ledger.verify()
    assert not proof["unchanged"]
    assert proof["changed"] == ["results/days.parquet", "results/meta.json"]
    by_path = {r["path"]: r for r in proof["files"]}
    assert by_path["results/meta.json"]["unchanged"] is False
    assert by_path["results/days.parquet"]["unchanged"] is True and by_path["results/days.parquet"]["mtime_unchanged"] is False


def test_guard_refuses_writes_under_the_audited_tree(audited, tmp_path):
    root, f, ledger = audited
    outside = tmp_path / "elsewhere.txt"
    with ledger.guard():
        with open(f, "r") as fh:
            assert fh.read() == '{"p99": 1.5}'
        with pytest.raises(ReadOnlyViolation):
            open(f, "w")
        with pytest.raises(ReadOnlyViolation):
            (root / "results" / "new.json").write_text("{}")
        with pytest.raises(ReadOnlyViolation):
            os.open(f, os.O_WRONLY)
        outside.write_text("allowed")  # not under the audited root
    assert f.read_text() == '{"p99": 1.5}' and not (root / "results" / "new.json").exists()
    assert outside.read_text() == "allowed"
    assert len(ledger.violations) == 3 and all("results/" in v for v in ledger.violations)
    open(f, "r").close()  # the guard is gone after the block
    assert not ledger.verify()["unchanged"]  # refused write attempts fail the proof


def test_gate_and_report_files(tmp_path):
    ok = Check(id="splits.segments", family="splits", claim="c")
    bad = Check(id="protocol.hashes", family="protocol", claim="c")
    bad.fail("results/milan/greedy/seed0/days.parquet: obs_spec_hash differs — a different observation spec")
    header = {"profile": "smoke", "datasets": ["milan"], "methods": ["greedy"], "config_hash": "x"}
    ro = {"files": [], "changed": [], "write_attempts": [], "unchanged": True}
    failed = (f"{tmp_path / 'r.json'}: the leakage audit failed (1 finding(s)); no table is built from a pipeline "
              f"that fails it — fix each finding (below, and in {tmp_path / 'r.md'}), then run "
              f"`snakemake --cores 2 tables`")
    for checks, expected in (([ok], []), ([ok, bad], [failed, f"protocol.hashes: {bad.failures[0]}"])):
        report = build_report(checks=checks, read_only=ro, header=header)
        write_report(report, json_path=tmp_path / "r.json", md_path=tmp_path / "r.md")
        assert gate(tmp_path / "r.json") == expected
        assert report["families"]["protocol"]["passed"] is (not expected)
    assert "**FAIL**" in (tmp_path / "r.md").read_text()
    (tmp_path / "x.json").write_text(json.dumps({"checks": []}))
    assert gate(tmp_path / "x.json") == [
        f"{tmp_path / 'x.json'}: not an audit report (lacks 'passed'); delete {tmp_path / 'x.json'} and run "
        f"`snakemake --cores 2 tables` to audit the tree afresh"]
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r.json", "r.md", "x.json"]  # no temp files left
