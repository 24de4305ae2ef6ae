"""The hashes and evaluated days every result file must carry, recomputed from config.yaml and meta.json.

The observation-spec hash comes from `dswm.env.obs_spec_hash` on the dataset grid of meta.json and the
scenario of config.yaml, the scenario hash from `dswm.config.Scenario.hash`, the eval-days hash from
`dswm.evaluation.eval_days_hash` of the days config.yaml picks (cut to the profile's limit), never of the days
a result file says it evaluated.
"""
from __future__ import annotations

from audits.context import AuditContext, AuditInputError
from audits.splits import expected_eval_days


def _grid(ctx: AuditContext, ds: str):
    from dswm.env import Grid

    g = ctx.meta(ds).get("grid", {})
    try:
        return Grid(rows=int(g["rows"]), cols=int(g["cols"]), cell_m=float(g["cell_m"]))
    except (KeyError, TypeError, ValueError) as exc:
        raise AuditInputError(f"{ctx.rel(ctx.meta_path(ds))}: grid {g!r} lacks rows/cols/cell_m") from exc


def expected_result_days(ctx: AuditContext, ds: str) -> dict[str, list[int]]:
    """{"id": [...], "ood": [...]} tensor days a result file must hold: the configured eval days, the first
    `profiles.<profile>.eval_days.<split>` of each when the profile limits them."""
    days = expected_eval_days(ctx, ds)
    limits = ctx.resolved["run"].get("eval_days", {})
    return {k: v[: limits[k]] if limits.get(k) else v for k, v in days.items()}


def expected_hashes(ctx: AuditContext, ds: str) -> dict[str, str]:
    """{"obs_spec_hash", "eval_days_hash", "scenario_hash"} a result file of dataset `ds` must carry."""
    from dswm.env import obs_spec_hash
    from dswm.evaluation import eval_days_hash

    days = expected_result_days(ctx, ds)
    labels = [d["label"] for d in ctx.meta(ds)["days"]]
    eval_hash = eval_days_hash(ds, days, labels)
    return {"obs_spec_hash": obs_spec_hash(_grid(ctx, ds), ctx.scenario), "eval_days_hash": eval_hash,
            "scenario_hash": ctx.scenario.hash()}
