"""The slices each rule passes its job: what the job reads, in canonical form (:func:`param`), which is the job's
rerun trigger; and :class:`Untracked`, a value passed beside the slice that triggers nothing. The extra runs'
slices (variants, workflow/rules/extra.smk) and the probe's (workflow/rules/probes.smk) are the main jobs' slices
of the changed settings.
"""
from __future__ import annotations

import dataclasses
import json
from typing import Any

from dswm.config import ConfigError, canonical_json, to_plain
from dswm.settings.model import Settings
from dswm.settings.variants import (ROOM_FILL_ARMS, ROOM_FILL_CANDIDATE, Variant, probe_jobs, room_fill_variant,
                                    variant_days, variant_settings)


@dataclasses.dataclass(frozen=True)
class Untracked:
    """A value a rule passes its job that is not part of its rerun trigger (Snakemake compares only plain
    params): how a job reports or tags its run, never what it computes."""

    value: Any
    """The value the job receives (``params.<name>.value``)."""


def param(obj: Any) -> str:
    """A rule's ``params`` value: ``obj`` in canonical JSON (equal settings give equal text)."""
    return canonical_json(obj)


def read_param(text: str) -> dict:
    """A job's side of :func:`param`: the plain mapping back."""
    return json.loads(text)


def runtime(settings: Settings) -> dict:
    """The :class:`Runtime` part of ``evaluation``, plain."""
    return {"device": settings.evaluation.device, "torch_threads": settings.evaluation.torch_threads}


def prep_slice(settings: Settings, dataset: str) -> dict:
    """What the ``demo_raw`` and ``prepare`` jobs of ``dataset`` read: its section and the common one."""
    return {"dataset": dataset, "settings": to_plain(getattr(settings.datasets, dataset)),
            "common": to_plain(settings.datasets.common)}


def eda_slice(settings: Settings) -> dict:
    """What the ``eda`` job reads: the share of cells of the "top cells" statistic."""
    return {"top_share_frac": settings.datasets.common.top_share_frac}


def mlflow_slice(settings: Settings) -> dict:
    """The rerun trigger of the ``mlflow_init`` job: the experiment's name (:func:`experiment_slice`). Where it creates
    the store and the experiment (``tracking_uri`` or ``store``, ``artifacts``) and how it asks a server (``http``)
    travel beside it (:func:`tracking`): a new store or server reruns no job, the workflow's ``onstart`` creates
    them there before any job logs."""
    return experiment_slice(settings)


def experiment_slice(settings: Settings) -> dict:
    """The part of ``mlflow`` in the slice of a job that logs a run: the experiment's name alone (a renamed
    experiment receives every job's run again). The rest of the section travels beside the slice as
    :func:`tracking`, so a change of the server, the store, the batch size or the HTTP retries reruns no job."""
    return {"experiment": settings.mlflow.experiment}


def tracking(settings: Settings) -> "Untracked":
    """The whole ``mlflow`` section, plain, as an :class:`Untracked` param (``params.tracking``): where and how a job
    logs its run, never what it computes."""
    return Untracked(to_plain(settings.mlflow))


def calibrate_slice(settings: Settings) -> dict:
    """What the ``calibrate`` job reads: the calibration, the scenario less the value it calibrates, and the
    device and threads (:class:`Runtime`)."""
    scenario = to_plain(settings.scenario)
    scenario.pop("demand_intensity")
    return {"calibration": to_plain(settings.calibration), "scenario": scenario, "runtime": runtime(settings)}


def train_slice(settings: Settings, method: str, dataset: str | None = None, seed: int | None = None) -> dict:
    """What a ``train`` job of ``method`` reads: the profile, the scenario, the device and threads
    (:class:`Runtime`), the MLflow experiment (:func:`experiment_slice`), and the method with only its training
    settings (so decision-time settings never retrain); for a job of the sample-efficiency probe (:func:`probe_jobs`,
    given its ``dataset`` and ``seed``) also ``snapshots``: {"fractions": ``figures.sample_efficiency.fractions``}."""
    m = settings.methods[method]
    cls = m.controller_class
    entry = dataclasses.replace(m, options=cls.training_settings(m.options))
    job = {"profile": settings.profile, "scenario": to_plain(settings.scenario), "runtime": runtime(settings),
           "mlflow": experiment_slice(settings), "method": to_plain(entry)}
    if dataset is not None and seed is not None and (dataset, method, int(seed)) in probe_jobs(settings):
        job["snapshots"] = {"fractions": list(settings.figures.sample_efficiency.fractions)}
    return job


def evaluate_slice(settings: Settings, method: str) -> dict:
    """What an ``evaluate`` job of ``method`` reads: the profile, the day limits, the scenario, the evaluation
    settings, the MLflow experiment (:func:`experiment_slice`), and the method with all its settings."""
    return {"profile": settings.profile, "eval_days": to_plain(settings.run.eval_days),
            "scenario": to_plain(settings.scenario), "evaluation": to_plain(settings.evaluation),
            "mlflow": experiment_slice(settings), "method": to_plain(settings.methods[method])}


def tables_slice(settings: Settings) -> dict:
    """What the ``tables`` job reads: the profile, the tables section, the datasets and the methods' rows."""
    return {"profile": settings.profile, "tables": to_plain(settings.tables), "datasets": list(settings.run.datasets),
            "methods": [to_plain(m.spec) for m in settings.methods.values()]}


def audit_slice(settings: Settings) -> dict:
    """What the audit reads: every setting but the display ones, the selection's, the figures', the resources and
    MLflow's (the audit reads files, never the tracking store)."""
    return to_plain(dataclasses.replace(settings, display=None, selection=None, figures=None, resources=None,
                                        mlflow=None))


def select_slice(settings: Settings) -> dict:
    """What the ``select`` job reads: the profile, the selection, the scenario, the evaluation settings and the
    planner method with all its settings.

    Raises:
        ConfigError: ``selection.planner_method`` is not in ``methods.run``. Only the ``select`` rule needs it, so
            the rule builds this slice when its job is built (every other target runs without it).
    """
    name = settings.selection.planner_method
    if name not in settings.methods:
        raise ConfigError(f"config.yaml: key 'selection.planner_method' is {name!r}, which 'methods.run' does not "
                          f"list (found {', '.join(settings.methods)}); the select target chooses that method's "
                          f"planner values: add {name!r} to 'methods.run', or name a planner method of it in "
                          f"'selection.planner_method'")
    return {"profile": settings.profile, "selection": to_plain(settings.selection),
            "scenario": to_plain(settings.scenario), "evaluation": to_plain(settings.evaluation),
            "method": to_plain(settings.methods[name])}


def _with_intensity_scale(job: dict, variant: Variant) -> dict:
    """``job`` with ``intensity_scale``, the factor of u applied after calibration, for a variant with a u change."""
    factor = variant.get("u")
    return {**job, "intensity_scale": float(factor)} if factor is not None else job


def variant_train_slice(settings: Settings, method: str, variant: Variant) -> dict:
    """What an ``extra_train`` job of ``method`` under ``variant`` reads: :func:`train_slice` of the variant's
    settings, with ``intensity_scale`` for a u variant. A do variant changes a decision-time setting only, so its
    slice is the main train job's (no training of its own)."""
    return _with_intensity_scale(train_slice(variant_settings(settings, variant, method), method), variant)


def variant_evaluate_slice(settings: Settings, method: str, variant: Variant) -> dict:
    """What an ``extra_evaluate`` job reads: :func:`evaluate_slice` of the variant's settings with the day limits
    of its figure (:func:`variant_days`: ``figures.eval_days``, or the foresight grid's or the headroom map's),
    and ``intensity_scale`` for a u change."""
    job = evaluate_slice(variant_settings(settings, variant, method), method)
    job["eval_days"] = to_plain(variant_days(settings, variant))
    return _with_intensity_scale(job, variant)


def room_fill_slice(settings: Settings, arm: str) -> dict:
    """What a ``room_fill_evaluate`` job of ``arm`` (``dswm.settings.ROOM_FILL_ARMS``) reads: its method's evaluate
    slice under the regime's variant (the main one at the scenario's own cell), on the profile's test days
    (``profiles.<p>.eval_days``) cut to ``figures.room_fill.eval_days``; the candidate's slice also holds
    ``room_fill`` (its fit job's settings; the rho_k and gamma come from that job)."""
    method, variant, rf = ROOM_FILL_ARMS[arm], room_fill_variant(settings), settings.figures.room_fill
    job = evaluate_slice(settings, method) if variant is None else variant_evaluate_slice(settings, method, variant)
    own, cut = settings.run.eval_days, rf.eval_days
    job["eval_days"] = {s: getattr(own, s) if getattr(cut, s) is None else
                        getattr(cut, s) if getattr(own, s) is None else min(getattr(own, s), getattr(cut, s))
                        for s in ("id", "ood")}
    if arm == ROOM_FILL_CANDIDATE:
        job["room_fill"] = to_plain(rf)
    return job


def variant_retrains(settings: Settings, method: str, variant: Variant) -> bool:
    """True when ``method``'s training source trains again under ``variant`` (its train slice differs from the
    main train job's: K changes the action size, u the reward); False for a method that does not learn."""
    source = settings.methods[method].training_source
    if source is None:
        return False
    return variant_train_slice(settings, source, variant) != train_slice(settings, source)


def probe_slice(settings: Settings, method: str) -> dict:
    """What a ``probe`` job of ``method`` reads: :func:`evaluate_slice` less the day limits (the probe runs one
    fixed day, the first ID test day): the method with all its settings, as its evaluation."""
    return {k: v for k, v in evaluate_slice(settings, method).items() if k != "eval_days"}


def figures_slice(settings: Settings) -> dict:
    """What a figure job of the results reads: the tables' slice (profile, tables, datasets, the methods' rows),
    the MLflow experiment (the runs its figure is attached to; :func:`experiment_slice`) and the ``figures``
    section."""
    return {**tables_slice(settings), "mlflow": experiment_slice(settings), "figures": to_plain(settings.figures)}
