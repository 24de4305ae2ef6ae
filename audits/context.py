"""What the audit reads, read once and only through the ledger: prepared data, raw files, results.

The EXPECTED facts (which days are training days, which eval days, which hashes) are derived here from the
run's typed settings (:class:`dswm.settings.Settings`, resolved once from config.yaml), never from the files
under audit; the files are then compared against them.
"""
from __future__ import annotations

import datetime as dt
import importlib
from functools import cached_property
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from audits.ledger import ReadLedger

if TYPE_CHECKING:
    from dswm.settings import Settings
    from prep.config import DatasetConfig


class AuditInputError(RuntimeError):
    """A file the audit needs is missing or unreadable; the message names it."""


def label_range(first: Any, last: Any) -> list[str]:
    """Day labels of an inclusive segment: ISO dates for dates, "d<n>" for day numbers."""
    try:
        a, b = int(str(first)), int(str(last))
        return [f"d{n}" for n in range(a, b + 1)]
    except ValueError:
        a, b = dt.date.fromisoformat(str(first)), dt.date.fromisoformat(str(last))
        return [(a + dt.timedelta(days=k)).isoformat() for k in range((b - a).days + 1)]


def label_order(label: str) -> int:
    """A sortable number of a day label (date ordinal, or the day number of "d<n>")."""
    return int(label[1:]) if label.startswith("d") else dt.date.fromisoformat(label).toordinal()


class AuditContext:
    """The audited tree and the settings it was produced under.

    Args:
        root: the workflow's working directory (holds results/ and the raw data paths of the settings).
        settings: the run's settings (config.yaml plus any --config overrides, resolved once).
        ledger: the read ledger (one is created for `root` when omitted).
        read_probes: whether the sample-efficiency probe's files are part of this audit. The workflow's main
            report (the tables' gate) leaves them out, so its inputs are the tables' sources alone; the probe
            report (`audit_probes`, run by `figures`) reads them.
        read_learning: whether the learning runs under results/learning/ are part of this audit (the learning
            report, `audit_learning`, run by `learning`, reads them; the tables' report does not).
        read_extra: whether the figures' extra runs under results/extra/ are part of this audit (the extra report,
            `audit_extra`, run by `figures`, reads them; the tables' report does not).
        extra_runs: (dataset, variant, method, seed) of every extra run the figures draw, as the workflow lists them
            (None: derived from the settings' figures section, ``audits.extra.extra_runs``).
    """

    def __init__(self, *, root: Path | str, settings: Settings, ledger: ReadLedger | None = None,
                 read_probes: bool = True, read_learning: bool = True, read_extra: bool = True,
                 extra_runs: list | None = None):
        self.root = Path(root).resolve()
        self.read_probes = read_probes
        self.read_learning = read_learning
        self.read_extra = read_extra
        self.extra_runs = extra_runs
        self.settings = settings
        self.profile = settings.profile
        self.datasets = list(settings.run.datasets)
        self.methods = list(settings.methods)
        self.results = self.root / "results"
        self.ledger = ledger or ReadLedger(root=self.root, guarded=[self.root])
        self._meta: dict[str, dict] = {}
        self._tensor: dict[str, Any] = {}
        self._raw: dict[str, Any] = {}
        self.cache: dict[str, Any] = {}
        """Values checks share (e.g. statistics recomputed from raw files), keyed by the module that owns them."""

    # ---- settings-derived expectations ----------------------------------------------------------------
    @property
    def intensity_calibrated(self) -> bool:
        """True when ``scenario.demand_intensity`` is ``calibrate``: the jobs took u from the calibrate record."""
        return self.settings.scenario.calibrates

    @property
    def calibration_record_path(self) -> Path:
        """The calibrate rule's record (``dswm.settings.CALIBRATION_RECORD``) under the audited root."""
        from dswm.settings import CALIBRATION_RECORD

        return self.root / CALIBRATION_RECORD

    @cached_property
    def scenario(self):
        """The scenario the jobs ran under: the settings', with u read from the calibrate rule's record when
        ``scenario.demand_intensity`` is ``calibrate`` (``dswm.settings.calibrated_scenario``, the jobs' own
        function, so the expected hashes use the number the jobs used).

        Raises:
            AuditInputError: u is ``calibrate`` and the record is missing or not valid (the message names the file
                and the key).
        """
        from dswm.config import ConfigError
        from dswm.settings import calibrated_scenario

        if not self.intensity_calibrated:
            return self.settings.scenario
        path = self.calibration_record_path
        try:
            self.ledger.track(path)
            return calibrated_scenario(self.settings.scenario, path)
        except (FileNotFoundError, ConfigError) as exc:
            msg = str(exc).replace(str(path), self.rel(path))
            raise AuditInputError(f"{msg} (scenario.demand_intensity is 'calibrate': the jobs took u from this "
                                  f"record)") from exc

    def section(self, ds: str) -> DatasetConfig:
        """The typed ``datasets.<ds>`` section."""
        return getattr(self.settings.datasets, ds)

    def split_cfg(self, ds: str) -> dict[str, list[str]]:
        """{"train": [first, last], "test": [first, last]} of datasets.<ds>.split."""
        split = self.section(ds).split
        return {"train": list(split.train), "test": list(split.test)}

    def calendar(self, ds: str) -> list[tuple[str, str]]:
        """Expected (label, split) of every tensor day, from the settings alone: training segment then test."""
        seg = self.split_cfg(ds)
        return [(lab, s) for s in ("train", "test") for lab in label_range(*seg[s])]

    def expected_split_of(self, ds: str) -> dict[str, str]:
        """{label: "train"|"test"} from the settings."""
        return dict(self.calendar(ds))

    def train_index(self, ds: str) -> np.ndarray:
        """Tensor day indices whose label the settings put in the training segment (labels from meta.json)."""
        want = self.expected_split_of(ds)
        return np.array([d["index"] for d in self.meta(ds)["days"] if want.get(d["label"]) == "train"],
                        dtype=np.int64)

    def test_index(self, ds: str) -> np.ndarray:
        """Tensor day indices whose label the settings put in the test segment."""
        want = self.expected_split_of(ds)
        return np.array([d["index"] for d in self.meta(ds)["days"] if want.get(d["label"]) == "test"],
                        dtype=np.int64)

    def seeds(self, ds: str) -> list[int]:
        return [int(s) for s in self.settings.seeds(ds)]

    def methods_on(self, ds: str) -> list[str]:
        """The methods evaluated on ``ds`` (``methods.only_on`` may restrict a method to some datasets)."""
        return [m for m in self.settings.methods_on(ds) if m in self.methods]

    def jobs(self) -> list[tuple[str, str, int]]:
        """Every (dataset, method, seed) of the selected profile."""
        return self.settings.jobs()

    def learns(self, method: str) -> bool:
        """Whether the method trains (its class declares `learns = True`)."""
        return bool(self.settings.methods[method].learns)

    @cached_property
    def training_sources(self) -> dict[str, str]:
        """{learning method: the method whose trained model it evaluates}, from the settings."""
        return self.settings.training_sources()

    def training_source(self, method: str) -> str:
        """The method whose train job fitted the model `method` evaluates (`method` itself unless it shares)."""
        return self.training_sources.get(method, method)

    @cached_property
    def percentile(self) -> float:
        return float(self.settings.datasets.common.norm_percentile)

    @cached_property
    def kappa_reference(self) -> str:
        return str(self.settings.datasets.common.kappa_reference)

    # ---- paths ----------------------------------------------------------------------------------------
    def data_dir(self, ds: str) -> Path:
        return self.results / "data" / ds

    def meta_path(self, ds: str) -> Path:
        return self.data_dir(ds) / "meta.json"

    def tensor_path(self, ds: str) -> Path:
        return self.data_dir(ds) / "demand.parquet"

    def run_dir(self, ds: str, method: str, seed: int) -> Path:
        return self.results / ds / method / f"seed{seed}"

    def rel(self, path: Path | str) -> str:
        return self.ledger.rel(path)

    # ---- prepared data --------------------------------------------------------------------------------
    def meta(self, ds: str) -> dict:
        """meta.json of a prepared dataset (read once, through the ledger)."""
        if ds not in self._meta:
            try:
                self._meta[ds] = self.ledger.read_json(self.meta_path(ds))
            except (FileNotFoundError, ValueError) as exc:
                raise AuditInputError(f"{self.rel(self.meta_path(ds))}: cannot read ({exc})") from exc
        return self._meta[ds]

    def tensor(self, ds: str):
        """The prepared tensor as the environment sees it (prep.tensor.load)."""
        if ds not in self._tensor:
            from prep.tensor import load

            try:
                self.ledger.track(self.meta_path(ds))
                self.ledger.track(self.tensor_path(ds))
                self._tensor[ds] = load(self.data_dir(ds))
            except (FileNotFoundError, ValueError) as exc:
                raise AuditInputError(f"{self.rel(self.tensor_path(ds))}: cannot load ({exc})") from exc
        return self._tensor[ds]

    # ---- raw data -------------------------------------------------------------------------------------
    def raw_candidates(self, ds: str) -> list[Path]:
        """Files that may be the raw inputs: the demo tree results/raw/<ds>/ or datasets.<ds>.raw_files."""
        meta = self.meta(ds)
        if meta.get("source") == "demo":
            base = self.results / "raw" / ds
            return sorted(p for p in base.rglob("*") if p.is_file()) if base.is_dir() else []
        out: list[Path] = []
        for pat in self.section(ds).raw_files:
            p = Path(pat) if Path(pat).is_absolute() else self.root / pat
            out.extend(sorted(p.parent.glob(p.name)) if any(c in p.name for c in "*?[") else [p])
        return [p for p in out if p.is_file()]

    def raw_paths(self, ds: str) -> list[Path]:
        """The raw files meta.json names as its sources, located and checked by size and SHA-256.

        Raises:
            AuditInputError: a recorded source is missing, or its bytes differ from the recorded hash.
        """
        meta = self.meta(ds)
        by_name: dict[str, list[Path]] = {}
        for p in self.raw_candidates(ds):
            by_name.setdefault(p.name, []).append(p)
        out = []
        for src in meta.get("sources", []):
            hits = by_name.get(src["name"], [])
            if not hits:
                raise AuditInputError(f"{self.rel(self.meta_path(ds))}: source {src['name']!r} is not among the "
                                      f"raw files of {ds} (looked in {'results/raw/' + ds if meta.get('source') == 'demo' else 'datasets.' + ds + '.raw_files'})")
            fp = [self.ledger.before[self.ledger.track(h)] for h in hits]
            match = [h for h, f in zip(hits, fp) if f.sha256 == src["sha256"] and f.bytes == src["bytes"]]
            if not match:
                raise AuditInputError(f"{self.rel(hits[0])}: SHA-256 {fp[0].sha256[:16]}.. / {fp[0].bytes} bytes "
                                      f"differ from the source recorded in {self.rel(self.meta_path(ds))} "
                                      f"({src['sha256'][:16]}.. / {src['bytes']} bytes)")
            out.append(match[0])
        if not out:
            raise AuditInputError(f"{self.rel(self.meta_path(ds))}: no source files recorded")
        return out

    def raw(self, ds: str):
        """The dataset's crop in raw units, rebuilt from its raw files by the `prep` readers (all days).

        Returns:
            prep.tensor.RawTensor (values (D, 144, R, C) float64).
        """
        if ds not in self._raw:
            paths = self.raw_paths(ds)
            try:
                module = importlib.import_module(f"prep.{ds}")
                self._raw[ds] = module.build(self.section(ds), paths)
            except (ImportError, ValueError, OSError) as exc:
                raise AuditInputError(f"{ds}: rebuilding the raw crop from {[self.rel(p) for p in paths][:3]} "
                                      f"failed ({exc})") from exc
        return self._raw[ds]
