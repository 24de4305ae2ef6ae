"""Protocol family, part 3: the clairvoyant methods are the bounds, and nothing else.

* `check_clairvoyant_bounds`: every method whose controller receives the day's TRUE demand (its class declares
  ``clairvoyant``: the oracle, the perfect forecast, the per-slot ceiling) is tabulated as an upper bound, and each of
  its result files records that very controller class; a per-slot bound (its class declares ``places``: the ceiling)
  flew no fleet, so its result files record no energy.

Which methods see the future is a property of their code (``dswm.methods.base.Controller.clairvoyant``), derived
here from the settings, never from the files under audit; the files are then compared with it.
"""
from __future__ import annotations

from audits.context import AuditContext
from audits.protocol import result_path, result_record
from audits.report import Check

BOUND_CLASS = "upper bound"
"""The table class of the bounds (``dswm.methods.registry``): the rows a reader must not take for controllers."""
ENERGY_COLUMNS = ("energy_kj_per_slot", "energy_efficiency")


def check_clairvoyant_bounds(ctx: AuditContext) -> Check:
    """The methods that see the day's true demand are the tables' upper bounds, and their files say so."""
    import polars as pl

    from dswm.protocol.evaluation import METHOD_RECORD_KEY, read_method_record

    chk = Check(id="protocol.clairvoyant_bounds", family="protocol",
                claim=f"Every method whose controller receives the day's TRUE demand (its class declares "
                      f"clairvoyant: the oracle, the perfect forecast, the per-slot ceiling) is tabulated in the class "
                      f"{BOUND_CLASS!r}, never beside the controllers, and every result file of it records that "
                      f"controller class; a per-slot bound (its class declares places: the ceiling) flies no fleet, "
                      f"and its result files record no energy.")
    seen: dict[str, dict] = {}
    for name in ctx.methods:
        m = ctx.settings.methods[name]
        cls = m.controller_class
        if not cls.clairvoyant:
            continue
        seen[name] = {"class": m.target, "table_class": m.table_class, "places": bool(cls.places), "files": 0}
        if m.table_class != BOUND_CLASS:
            chk.fail(f"methods.{name}: {m.target} receives the day's true demand (clairvoyant), but the tables "
                     f"class it as {m.table_class!r}; expected {BOUND_CLASS!r} — a clairvoyant method would be "
                     f"read as a controller")
    for ds in ctx.datasets:
        for name in [m for m in ctx.methods_on(ds) if m in seen]:
            for seed in ctx.seeds(ds):
                path = result_path(ctx, ds, name, seed)
                rec = result_record(ctx, chk, path, read=read_method_record, key=METHOD_RECORD_KEY,
                                    holds=f"the controller class of {name}", job=f"{ds}/{name}/seed{seed}")
                if rec is None:
                    continue
                where = ctx.rel(path)
                if rec.get("class") != seen[name]["class"]:
                    chk.fail(f"{where}: {METHOD_RECORD_KEY} records class {rec.get('class')!r}; the settings give "
                             f"{name} {seen[name]['class']!r} — another controller wrote the result of a bound")
                if seen[name]["places"]:
                    days = pl.read_parquet(ctx.ledger.track(path), columns=list(ENERGY_COLUMNS))
                    flown = [c for c in ENERGY_COLUMNS if days[c].is_not_null().any()]
                    if flown:
                        chk.fail(f"{where}: {name} is a per-slot bound that flies no fleet, but its {flown} hold "
                                 f"values — the file was not written by the per-slot evaluation (FleetCore.place)")
                seen[name]["files"] += 1
    chk.evidence.update(clairvoyant=seen,
                        note="no method of the run is clairvoyant" if not seen else
                        "these methods received the day's true demand; they bound the controllers and are no "
                        "controllers themselves")
    return chk
