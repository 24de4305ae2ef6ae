"""How every job sets itself up: the one path that train, evaluate, select, the extra runs, the probe and the
world-model quality replay go through, so a fix to job setup is made once.

* :func:`set_up`            the typed runtime or evaluation settings, the scenario the job simulates (u from the
                            calibrate rule's record, times a u variant's factor) and the method, from the job's slice;
                            torch's threads, the allocator and subnormal flushing set (:func:`init_process`).
* :func:`open_run`          the job's one MLflow run (``dswm.pipeline.tracking.job_run``), logging and hashing the
                            slice as used.
* :func:`build_controller`  the job's controller.
* :func:`load_source_model` the model of the method's training source, checked against its manifest.
* :func:`load_tensor`, :func:`prepared_files_read`, :func:`log_demand_input`, :func:`workdir_relative`: the
  prepared demand tensor and the record of the files read.
"""
from __future__ import annotations

import dataclasses
import json
import shlex
import sys
from pathlib import Path
from typing import Any, Callable, Mapping, Sequence

import torch

from dswm.config import build, stable_hash, to_plain
from dswm.methods import registry
from dswm.methods.base import Controller
from dswm.methods.matmul import emulated_bfloat16_warning
from dswm.pipeline import tracking
from dswm.pipeline.allocator import keep_freed_memory
from dswm.pipeline.heap import freeze_heap
from dswm.pipeline.subnormals import flush_subnormals
from dswm.protocol.evaluation import evaluate
from dswm.settings import EvaluationSettings, MethodSettings, Runtime, calibrated_scenario, scale_intensity
from dswm.sim.core import FleetCore, core_from_tensor
from dswm.sim.scenario import Scenario
from prep.rawio import sha256_file


def load_tensor(tensor_dir: str | Path):
    """The prepared demand tensor of ``tensor_dir`` (``prep.tensor.load``)."""
    from prep.tensor import load

    return load(tensor_dir)


def workdir_relative(path: str | Path) -> str:
    """``path`` relative to the working directory (the workflow's root, where the audit resolves it), POSIX."""
    p = Path(path)
    if p.is_absolute():
        try:
            p = p.relative_to(Path.cwd())
        except ValueError:
            pass
    return p.as_posix()


def prepared_files_read(tensor_dir: str | Path) -> list[dict]:
    """The ``data_files_read`` of a training manifest: the files ``prep.tensor.load`` reads from ``tensor_dir``.

    Returns:
        [{"path": path relative to the working directory, "sha256": hex SHA-256 of the file}] for
        demand.parquet and meta.json, hashed before the job loads them.
    """
    from prep.tensor import META_FILE, TENSOR_FILE

    return [{"path": workdir_relative(Path(tensor_dir) / name), "sha256": sha256_file(Path(tensor_dir) / name)}
            for name in (TENSOR_FILE, META_FILE)]


def log_demand_input(run: tracking.JobRun, tensor_dir: str | Path, dataset: str, context: str) -> str:
    """Record the prepared demand tensor (``tensor_dir``/demand.parquet) as the run's MLflow dataset input, named
    ``dataset`` with the first 16 hex digits of its SHA-256 as digest; returns the full SHA-256."""
    from prep.tensor import TENSOR_FILE

    path = Path(tensor_dir) / TENSOR_FILE
    digest = sha256_file(path)
    run.log_dataset(path, name=dataset, digest=digest[:16], context=context)
    return digest


def prepare_process(threads: int) -> bool:
    """Flush subnormal floats to zero (before any worker thread starts: they inherit it), set torch's ``threads``,
    keep freed tensor memory in the heap and keep the cyclic collector off the imported libraries
    (:mod:`dswm.pipeline.heap`): every job's process (:func:`init_process`) and every benchmark's. Returns whether
    subnormals are flushed (False where the CPU has no such mode)."""
    flushed = flush_subnormals()
    torch.set_num_threads(threads)
    keep_freed_memory()
    freeze_heap()
    return flushed


def init_process(runtime: Runtime | EvaluationSettings) -> None:
    """:func:`prepare_process` with ``runtime.torch_threads``."""
    prepare_process(runtime.torch_threads)


@dataclasses.dataclass(frozen=True)
class JobSetup:
    """What a job that simulates builds from its slice (:func:`set_up`)."""

    job: dict
    """The slice as used: its scenario with u the number simulated; what the job's MLflow run logs and hashes."""
    settings: Any
    """The typed ``Runtime`` (train) or ``EvaluationSettings`` (the others) of the slice."""
    scenario: Scenario
    """The scenario the job simulates."""
    method: MethodSettings
    """The method's registration and typed settings."""

    @property
    def config_hash(self) -> str:
        """The hash of :attr:`job` (the run's ``config_hash`` tag)."""
        return stable_hash(self.job, length=12)


def set_up(job: Mapping[str, Any], key: str, cls: type, intensity: str | Path | None = None) -> JobSetup:
    """The typed ``job[key]`` (runtime or evaluation settings), scenario and method of a job, with the process set
    up (:func:`init_process`).

    Args:
        job: the plain slice its rule passes (``dswm.settings.*_slice``).
        key: "runtime" (train) or "evaluation"; ``cls`` its settings class.
        intensity: the calibrate rule's record, read when the slice's scenario says ``calibrate``; a variant's
            ``job["intensity_scale"]`` (``dswm.settings.scale_intensity``) multiplies the u it gives.
    """
    settings = build(cls, job[key], key)
    init_process(settings)
    scenario = calibrated_scenario(Scenario.from_dict(job["scenario"]), intensity)
    scenario = scale_intensity(scenario, float(job.get("intensity_scale", 1.0)))
    method = MethodSettings.from_plain(job["method"], "method")
    warn_emulated_bfloat16(method, settings.device)
    return JobSetup(job={**job, "scenario": to_plain(scenario)}, settings=settings, scenario=scenario, method=method)


def warn_emulated_bfloat16(method: MethodSettings, device: str, native: bool | None = None) -> str | None:
    """Print to the job's log (stderr) the warning of :func:`dswm.methods.matmul.emulated_bfloat16_warning` for the
    method's ``matmul_dtype`` on ``device``, and return it (None: nothing to warn of)."""
    message = emulated_bfloat16_warning(f"methods.{method.name}.matmul_dtype",
                                        getattr(method.options, "matmul_dtype", None), device, native)
    if message:
        print(f"WARNING: {message}", file=sys.stderr)
    return message


def open_run(s: JobSetup, *, mlflow_cfg: Mapping[str, Any], stage: str, dataset: str, method: str, seed: int,
             repo: str | Path, keep: Sequence[str | Path], kind: str = "main"):
    """The job's one MLflow run (``dswm.pipeline.tracking.job_run``): params the slice as used, ``config_hash``
    its hash; ``kind`` and ``stage`` as that function says."""
    return tracking.job_run(mlflow_cfg=mlflow_cfg, settings=s.job, stage=stage, dataset=dataset, method=method,
                            seed=seed, config_hash=s.config_hash, repo=repo, keep=keep, kind=kind)


def build_controller(s: JobSetup, method: str, seed: int) -> Controller:
    """The controller of ``method`` (its registration and options from :attr:`JobSetup.method`) on the job's
    device."""
    return registry.build(method, target=s.method.target, options=s.method.options, seed=seed,
                          device=s.settings.device)


def score_snapshot(s: JobSetup, *, tensor, method: str, seed: int, path: str | Path | None,
                   days: Mapping[str, Sequence[int]], progress_interval_s: float,
                   configure: Callable[[Controller], None] | None = None):
    """Evaluate a fresh controller of ``method``, with the model file ``path`` loaded (None: as built), on ``days``
    ({split: day indices}) in the evaluation's own environment and initial fleet (``s.settings``: the job's
    EvaluationSettings); its per-day rows. The evaluation seeds torch and numpy with ``seed`` each time, so a
    snapshot's number does not depend on the ones scored before it (the probe and learning-curve jobs).
    ``configure`` is applied to the loaded controller before it acts (a diagnostic's change, e.g.
    ``benchmarks/diagnose_sb3.py`` sampling an SB3 policy; no job passes one)."""
    ctrl = build_controller(s, method, seed)
    if path is not None:
        ctrl.load(path)
    if configure is not None:
        configure(ctrl)
    ev = s.settings
    return evaluate(tensor=tensor, controller=ctrl, scenario=s.scenario, seed=seed, limits={"id": None, "ood": None},
                    profile=s.job["profile"], device=ev.device, batch_days=ev.batch_days, trajectory=False,
                    progress_interval_s=progress_interval_s, days=days).days


def training_core(tensor, scenario: Scenario, device: str = "cpu", days: Sequence[int] | None = None) -> FleetCore:
    """A FleetCore over the TRAINING days only (``days``: those of them, e.g. a learning run's, which holds its
    validation days out); ``core.day_ids`` maps its days to tensor day indices.

    Raises:
        ValueError: a day of ``days`` that is no training day.
    """
    train = [int(d) for d in tensor.train_days]
    if days is not None:
        stray = [int(d) for d in days if int(d) not in train]
        if stray:
            raise ValueError(f"meta.json of {tensor.meta['dataset']}: day(s) {stray} are no training days; a train "
                             f"job fits on training days only")
        train = [int(d) for d in days]
    return core_from_tensor(tensor, scenario, train, device=device)


def load_source_model(run: tracking.JobRun, ctrl: Controller, m: MethodSettings, *, model: str | Path | None,
                      manifest: str | Path | None, what: str | None = None) -> dict:
    """Load the model of ``m``'s training source into ``ctrl`` when the method learns, after checking its hash
    (:func:`model_record`), and tag the run with it; returns the model record (the empty one for a method that does
    not learn).

    Raises:
        ValueError: a learning method without its source's model file or manifest (``what`` names the job).
    """
    if not ctrl.learns:
        return model_record(method=m.name)
    if model is None or manifest is None:
        raise ValueError(f"{what or m.name}: a learning method needs its training source's model file and "
                         f"train_manifest.json (found model={model!r}, manifest={manifest!r})")
    record = model_record(method=m.name, source=m.training_source or m.name, model=model, manifest=manifest)
    run.set_tags({"train_source": record["train_source"], "model_path": record["model"],
                  "model_sha256": record["model_sha256"]})
    ctrl.load(model)
    return record


def model_record(*, method: str, source: str | None = None, model: str | Path | None = None,
                 manifest: str | Path | None = None) -> dict:
    """What an evaluation records about the model it loads (``evaluation.MODEL_RECORD_FIELDS``).

    Args:
        method: the evaluated method.
        source: its training source (dswm.methods.registry.training_sources); None for a method that does not learn.
        model: the source's model file, hashed here, before it is loaded.
        manifest: the source's train_manifest.json; its ``model_sha256`` must be the model file's SHA-256.

    Raises:
        ValueError: the model file does not hash to the manifest's ``model_sha256``.
    """
    if source is None:
        return {"method": method, "train_source": None, "model": None, "model_sha256": None, "train_manifest": None}
    found = sha256_file(Path(model))
    with open(manifest, encoding="utf-8") as fh:
        want = json.load(fh).get("model_sha256")
    if found != want:  # a truncated or replaced file; the train job that writes it rebuilds it
        rel = shlex.quote(workdir_relative(model))
        raise ValueError(f"{model}: SHA-256 is {found}, expected {want} (model_sha256 of {manifest}) — not the model "
                         f"{source} trained for {method}; re-run the train job of {source}: `rm {rel}`, then the same "
                         f"snakemake command again (or add `--forcerun {rel}` to it)")
    return {"method": method, "train_source": source, "model": workdir_relative(model), "model_sha256": found,
            "train_manifest": workdir_relative(manifest)}


def method_record(m: MethodSettings, ctrl: Controller) -> dict:
    """What an evaluation records about the method it ran (``evaluation.METHOD_RECORD_FIELDS``).

    Args:
        m: the method's registration and typed settings (``MethodSettings`` of the job's slice).
        ctrl: the controller built from ``m``; its ``search_settings()`` is the BCD search it runs, or None.

    Returns:
        {"method": m.name, "class": m.target, "options": plain ``m.options``, "search": plain search settings or
        None}, every value plain JSON (``dswm.config.to_plain``).
    """
    search = ctrl.search_settings()
    return {"method": m.name, "class": m.target, "options": to_plain(m.options),
            "search": None if search is None else to_plain(search)}
