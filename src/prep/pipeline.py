"""Entry points used by the Snakemake rules: demo generation, preparation, and the rules' inputs."""
from __future__ import annotations

import logging
from pathlib import Path

from prep import tensor
from prep.config import CommonPrep, DatasetConfig
from prep.days import pick_eval_days
from prep.rawio import PrepError, expand_paths

log = logging.getLogger(__name__)

DEMO_DIR = "results/raw/{dataset}/demo"
DATA_DIR = "results/data/{dataset}"


def raw_inputs(cfg: DatasetConfig, dataset: str, *, root: Path | str = ".") -> list[str]:
    """The raw inputs of `prepare` for Snakemake: the demo directory, or the user's expanded raw files.

    Args:
        cfg: the dataset's typed section (``datasets.<dataset>``).
        dataset: dataset name.
        root: directory that relative raw paths are resolved against (the workflow's working directory).
    Returns:
        A list of paths (strings).
    """
    if cfg.source == "demo":
        return [DEMO_DIR.format(dataset=dataset)]
    return [str(p) for p in expand_paths(cfg.raw_files, root=Path(root))]


def reference_input(common: CommonPrep, dataset: str) -> list[str]:
    """[meta.json of the kappa reference dataset] for every other dataset, [] for the reference itself."""
    ref = common.kappa_reference
    return [] if dataset == ref else [f"{DATA_DIR.format(dataset=ref)}/{tensor.META_FILE}"]


def generate_demo(cfg: DatasetConfig, dataset: str, out_dir: Path | str) -> list[Path]:
    """Writes the demo raw files of `dataset` (typed section `cfg`) into `out_dir` (see prep.demo)."""
    from prep.demo import generate

    files = generate(dataset, cfg, Path(out_dir))
    log.info("%s demo: wrote %d raw file(s) to %s", dataset, len(files), out_dir)
    return files


def _collect(paths: list[str]) -> list[Path]:
    out: list[Path] = []
    for p in map(Path, paths):
        if p.is_dir():
            out.extend(sorted(q for q in p.iterdir() if q.is_file() and not q.name.startswith(".")))
        elif p.is_file():
            out.append(p)
        else:
            raise PrepError(f"raw input {p}: no such file or directory")
    return out


def prepare_dataset(cfg: DatasetConfig, common: CommonPrep, dataset: str, *, raw: list[str], out_dir: Path | str,
                    reference_meta: str | None) -> dict:
    """Prepares one dataset: raw files -> demand.parquet + meta.json in `out_dir` (atomically).

    Args:
        cfg: the dataset's typed section (``datasets.<dataset>``); common: ``datasets.common``.
        dataset: "milan", "shanghai" or "yjmob".
        raw: raw files and/or directories holding them.
        out_dir: results/data/{dataset}.
        reference_meta: meta.json of the kappa reference dataset (None for the reference itself).
    Returns:
        The written meta dict.
    """
    paths = _collect(raw)
    if not paths:
        raise PrepError(f"{dataset}: no raw file found in {raw}")
    log.info("%s: preparing from %d raw file(s), source=%s", dataset, len(paths), cfg.source)
    if dataset == "milan":
        from prep.milan import build
    elif dataset == "shanghai":
        from prep.shanghai import build
    else:
        from prep.yjmob import build
    raw_tensor = build(cfg, paths)  # type: ignore[arg-type]
    eval_days = pick_eval_days(raw_tensor.days, raw_tensor.weekend, cfg.eval_days, dataset=dataset)
    labels = [d.label for d in raw_tensor.days]
    empty_eval = [labels[i] for s in ("id", "ood") for i in eval_days[s] if labels[i] in raw_tensor.empty_days]
    if empty_eval:  # the config check refuses such an allowance; this guards the tensor itself
        raise PrepError(f"{dataset}: evaluation day(s) {empty_eval} have no record; expected data on every "
                        f"evaluation day (remove them from datasets.{dataset}.allow_empty_days)")
    ref_mean = None
    if dataset != common.kappa_reference:
        if reference_meta is None:
            raise PrepError(f"{dataset}: kappa needs the meta.json of {common.kappa_reference}")
        ref = tensor.read_meta(reference_meta, keys=("dataset", "kappa", "train_mean_normalized"))
        if ref.get("dataset") != common.kappa_reference:
            raise PrepError(f"{reference_meta}: expected the meta.json of {common.kappa_reference!r}, found "
                            f"dataset {ref.get('dataset')!r}")
        ref_mean = float(ref["train_mean_normalized"]) * float(ref["kappa"])
    demand, meta = tensor.finalize(raw_tensor, common=common, cfg=cfg, source=cfg.source, eval_days=eval_days,
                                   reference_mean=ref_mean)
    tensor.write(out_dir, demand, meta)
    log.info("%s: wrote %s (days=%d, grid=%dx%d) p99=%.6g kappa=%.6g zero_cell_rate=%.4f top5_share=%.4f "
             "eval_days=%s dropped=%s", dataset, out_dir, demand.shape[0], demand.shape[2], demand.shape[3],
             meta["p99"], meta["kappa"], meta["zero_cell_rate"], meta["top5_share"], meta["eval_days"],
             meta["dropped"])
    return meta
