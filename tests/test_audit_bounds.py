"""The audit knows the clairvoyant methods: they are the tables' upper bounds, their files say so (audits.bounds)."""
from __future__ import annotations

import dataclasses
import json

import polars as pl

from audit_fixtures import clean, method_record, one_torch_thread, tree, write_record, write_results  # noqa: F401
from audits import bounds
from audits.context import AuditContext
from dswm.protocol.evaluation import read_method_record, read_model_record, write_days
from dswm.settings import resolve

CEILING = "dswm.methods.ceiling:CeilingController"


def with_ceiling(root):
    """The tree's settings with the ceiling in `methods.run`, and its result files written as its evaluation writes
    them (no energy: it flies no fleet)."""
    cfg = json.loads((root / "config.json").read_text())
    cfg["methods"]["run"].append("ceiling")
    settings = resolve(cfg)
    for ds in settings.run.datasets:
        path = write_results(settings, root, ds, "ceiling", 0)
        rewrite(path, lambda df: df.with_columns(pl.lit(None, pl.Float64).alias("energy_kj_per_slot"),
                                                 pl.lit(None, pl.Float64).alias("energy_efficiency")))
    return settings


def rewrite(path, change=lambda df: df, method_rec=None):
    """Rewrites a result file with ``change`` applied (and another method record), then its content record, as a
    faulty evaluation would have written them."""
    days, model, method = pl.read_parquet(path), read_model_record(path), read_method_record(path)
    write_days(change(days), path, model, method_rec if method_rec is not None else method)
    write_record(path.parent)


def test_the_ceiling_is_known_as_a_clairvoyant_bound_and_a_clean_run_passes(tree):
    root, _ = tree
    settings = with_ceiling(root)
    chk = bounds.check_clairvoyant_bounds(AuditContext(root=root, settings=settings))
    assert chk.passed, chk.failures
    assert chk.id == "protocol.clairvoyant_bounds"
    assert chk.evidence["clairvoyant"] == {"ceiling": {"class": CEILING, "table_class": "upper bound", "places": True,
                                                       "files": 2}}


def test_a_run_without_a_clairvoyant_method_passes_and_says_so(clean):
    root, settings = clean
    chk = bounds.check_clairvoyant_bounds(AuditContext(root=root, settings=settings))
    assert chk.passed and chk.evidence["clairvoyant"] == {}
    assert chk.evidence["note"] == "no method of the run is clairvoyant"


def test_a_clairvoyant_method_tabulated_beside_the_controllers_fails(tree):
    root, _ = tree
    settings = with_ceiling(root)
    methods = dict(settings.methods)
    methods["ceiling"] = dataclasses.replace(methods["ceiling"], table_class="model-free")
    chk = bounds.check_clairvoyant_bounds(AuditContext(root=root, settings=dataclasses.replace(settings,
                                                                                              methods=methods)))
    assert chk.failures == [f"methods.ceiling: {CEILING} receives the day's true demand (clairvoyant), but the tables "
                            f"class it as 'model-free'; expected 'upper bound' — a clairvoyant method would be read "
                            f"as a controller"]


def test_a_ceiling_result_with_energy_was_not_written_by_the_per_slot_evaluation(tree):
    root, _ = tree
    settings = with_ceiling(root)
    path = root / "results/yjmob/ceiling/seed0/days.parquet"
    rewrite(path, lambda df: df.with_columns(pl.lit(1616.0).alias("energy_kj_per_slot")))
    chk = bounds.check_clairvoyant_bounds(AuditContext(root=root, settings=settings))
    assert chk.failures == ["results/yjmob/ceiling/seed0/days.parquet: ceiling is a per-slot bound that flies no "
                            "fleet, but its ['energy_kj_per_slot'] hold values — the file was not written by the "
                            "per-slot evaluation (FleetCore.place)"]


def test_a_ceiling_result_written_by_another_controller_fails(tree):
    root, _ = tree
    settings = with_ceiling(root)
    path = root / "results/milan/ceiling/seed0/days.parquet"
    rewrite(path, method_rec={**method_record(settings, "ceiling"), "class": "dswm.methods.classical:GreedyController"})
    chk = bounds.check_clairvoyant_bounds(AuditContext(root=root, settings=settings))
    assert chk.failures == ["results/milan/ceiling/seed0/days.parquet: dswm.method_settings records class "
                            "'dswm.methods.classical:GreedyController'; the settings give ceiling "
                            f"'{CEILING}' — another controller wrote the result of a bound"]
