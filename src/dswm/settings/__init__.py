"""The settings of a run, resolved once: schema validation, profile selection, one typed :class:`Settings`.

``config.yaml`` holds every section; ``profiles:`` holds the three sizes of the same pipeline (demo, smoke,
paper). :func:`resolve` validates the file against the workflow's schema (:data:`SCHEMA`), selects the profile
and builds every section with the one typed builder (``dswm.config.build``), the methods' own settings
included. It runs once, while Snakemake parses the workflow, so a bad config stops the run before any job
starts, with a message that names the key, what was expected and what was found.

Jobs never see config.yaml: each rule passes its job the slice of :class:`Settings` the job reads, in canonical
form (:func:`dswm.config.canonical_json`, sorted keys), and that slice is the rule's rerun trigger. The slices
are built here (``*_slice``) and read back in the job by the same builder. Settings that change only how a
job reports (the progress bar's refresh interval; where and how its MLflow run is logged, :func:`tracking`) are
passed beside the slice as a typed object, which Snakemake does not compare, so changing them reruns nothing
(docs/PIPELINE.md).

One concern per module, every name re-exported here (``from dswm import settings as S``):

- :mod:`~dswm.settings.schema`: the schema check and its messages (:func:`validate_config`, :data:`SCHEMA`);
- :mod:`~dswm.settings.sections`: the typed sections (run, evaluation, calibration, selection, MLflow, tables,
  figures, resources);
- :mod:`~dswm.settings.model`: :class:`Settings` and :class:`MethodSettings`;
- :mod:`~dswm.settings.resolver`: :func:`resolve` and the cross-key checks;
- :mod:`~dswm.settings.calibration`: the demand intensity u and the calibrate rule's record;
- :mod:`~dswm.settings.variants`: the extra runs' variants and the sample-efficiency probe's jobs;
- :mod:`~dswm.settings.slices`: the slice each rule passes its job (:func:`param`, ``*_slice``, :class:`Untracked`);
- :mod:`~dswm.settings.learning`: the learning curves' section, learners, caps and slices (kept out of
  :class:`Settings`, so the tables' slices do not change with it).
"""
from dswm.config import ConfigError, build
from dswm.settings.calibration import CALIBRATION_RECORD, calibrated_scenario, intensity_inputs, read_intensity
from dswm.settings.learning import (LearningSettings, capped_settings, check_learning, learning_methods,
                                    learning_priority, learning_references, learning_score_slice, learning_settings,
                                    learning_train_slice)
from dswm.settings.model import REUSED_FILES, MethodSettings, Settings, evaluated_as, needs_gpu, reused_seed
from dswm.settings.resolver import (check_figures, check_profile_datasets, check_raw_files, resolve,
                                   select_profile)
from dswm.settings.schema import (SCHEMA, SETTINGS_MARKER, coerce_cli_strings, complete_schema, load_schema,
                                  settings_class, validate_config)
from dswm.settings.sections import (RoomFillSettings, CalibrationSettings, Display, DoProbeSettings, EvalDayLimits,
                                    EvaluationSettings, FiguresSettings, JobResources, MlflowHttp, MlflowSettings,
                                    ResourceSettings, RoomSettings, Runtime, RunSettings, SampleEfficiencySettings,
                                    ScalingSettings, SelectionSettings, SplitLabels, TablesSettings,
                                    WmQualitySettings, ForesightSettings, HeadroomSettings, figures_settings,
                                    resource_settings)
from dswm.settings.slices import (Untracked, audit_slice, calibrate_slice, eda_slice, evaluate_slice,
                                  experiment_slice, figures_slice, mlflow_slice, param, prep_slice, probe_slice,
                                  read_param, runtime, select_slice, tables_slice, tracking, train_slice,
                                  room_fill_slice, variant_evaluate_slice, variant_retrains, variant_train_slice)
from dswm.settings.variants import (ALGORITHM_1, HEADROOM_METHODS, PLANNERS, ROOM_FILL_ARMS, ROOM_FILL_CANDIDATE,
                                    SOURCE_METHODS, SOURCES, VARIANT_KINDS, Variant, check_room_fill, extra_jobs,
                                    extra_variants, figure_seeds, figure_variants, foresight_cells, foresight_jobs,
                                    headroom_jobs, headroom_variant, parse_variant, probe_jobs, probed_methods,
                                    room_fill_arms, room_fill_jobs, room_fill_variant, scale_intensity, variant_days,
                                    variant_methods, variant_settings)

__all__ = [
    "ConfigError", "build",
    "CALIBRATION_RECORD", "calibrated_scenario", "intensity_inputs", "read_intensity",
    "LearningSettings", "capped_settings", "check_learning", "learning_methods", "learning_priority",
    "learning_references", "learning_score_slice", "learning_settings", "learning_train_slice",
    "MethodSettings", "REUSED_FILES", "Settings", "evaluated_as", "needs_gpu", "reused_seed",
    "check_figures", "check_profile_datasets", "check_raw_files", "resolve", "select_profile",
    "SCHEMA", "SETTINGS_MARKER", "coerce_cli_strings", "complete_schema", "load_schema", "settings_class",
    "validate_config",
    "CalibrationSettings", "Display", "DoProbeSettings", "EvalDayLimits", "EvaluationSettings", "FiguresSettings",
    "JobResources", "MlflowHttp", "MlflowSettings", "ResourceSettings", "RoomSettings", "Runtime", "RunSettings",
    "SampleEfficiencySettings", "ScalingSettings", "SelectionSettings", "SplitLabels", "TablesSettings",
    "WmQualitySettings", "ForesightSettings", "HeadroomSettings", "RoomFillSettings", "figures_settings",
    "resource_settings",
    "Untracked", "audit_slice", "calibrate_slice", "eda_slice", "evaluate_slice", "experiment_slice",
    "figures_slice", "mlflow_slice", "param", "prep_slice", "probe_slice", "read_param", "runtime", "select_slice",
    "tables_slice", "tracking", "train_slice", "room_fill_slice", "variant_evaluate_slice", "variant_retrains",
    "variant_train_slice",
    "ALGORITHM_1", "HEADROOM_METHODS", "PLANNERS", "SOURCE_METHODS", "SOURCES", "VARIANT_KINDS", "Variant",
    "extra_jobs", "extra_variants", "figure_seeds", "figure_variants", "foresight_cells", "foresight_jobs",
    "headroom_jobs", "headroom_variant", "parse_variant", "probe_jobs", "probed_methods", "scale_intensity",
    "variant_days", "variant_methods", "variant_settings",
    "ROOM_FILL_ARMS", "ROOM_FILL_CANDIDATE", "check_room_fill", "room_fill_arms", "room_fill_jobs", "room_fill_variant",
]
