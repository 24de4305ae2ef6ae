"""The hashes and evaluated days every result file must carry, recomputed from the settings and meta.json.

`dswm.protocol.evaluation.result_hashes`, the evaluation's own, computes the three: the observation-spec hash on the
dataset grid of meta.json and the scenario of the settings, the scenario hash, and the eval-days hash of the days the
settings pick (cut to the profile's limit), never of the days a result file says it evaluated.
"""
from __future__ import annotations

from audits.context import AuditContext, AuditInputError
from audits.splits import expected_eval_days


def _grid(ctx: AuditContext, ds: str):
    from dswm.sim.core import Grid

    g = ctx.meta(ds).get("grid", {})
    try:
        return Grid(rows=int(g["rows"]), cols=int(g["cols"]), cell_m=float(g["cell_m"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise AuditInputError(f"{ctx.rel(ctx.meta_path(ds))}: grid {g!r} lacks rows/cols/cell_m") from exc


def expected_result_days(ctx: AuditContext, ds: str) -> dict[str, list[int]]:
    """{"id": [...], "ood": [...]} tensor days a result file must hold: the configured eval days, the first
    `profiles.<profile>.eval_days.<split>` of each when the profile limits them."""
    days = expected_eval_days(ctx, ds)
    limits = ctx.settings.run.eval_days
    return {k: v[: getattr(limits, k)] if getattr(limits, k) else v for k, v in days.items()}


def expected_hashes(ctx: AuditContext, ds: str) -> dict[str, str]:
    """{"obs_spec_hash", "eval_days_hash", "scenario_hash"} a result file of dataset `ds` must carry."""
    from dswm.protocol.evaluation import result_hashes

    labels = [d["label"] for d in ctx.meta(ds)["days"]]
    return result_hashes(ds, _grid(ctx, ds), ctx.scenario, expected_result_days(ctx, ds), labels)
