"""MLflow tracking of the workflow's jobs: one store, two experiments, one run per job.

The store is the SQLite file ``mlflow.store`` on one machine, or, where ``mlflow.tracking_uri`` names one, an MLflow
tracking server (on a cluster: PostgreSQL behind it, artifacts on the shared filesystem; docs/CLUSTER.md). The
store and its experiments are created once by the ``mlflow_init`` rule (:func:`init_store`): ``mlflow.experiment``
holds the tables' train and evaluate runs, ``<experiment>-figures`` the runs behind the figures only (extra runs,
probe, world-model quality), so the UI opens on the tables' runs. Every such job then opens exactly one run with
:func:`job_run`. A SQLite store inside the tree belongs to that tree: after the tree is copied or moved, the store's
absolute paths are made the copy's own (:func:`adopt_store`), so a job in the copy never writes into the tree it was
copied from. A run is tagged with its kind (:data:`RUN_KINDS`), its job key (stage/dataset/method/seed), the
working directory it ran in, the profile, the git commit and the hash of its
settings, and carries the settings slice it read as params. Metrics go out in batches (one round trip per batch
instead of one per value). When a job is rerun, the previous FINISHED runs of the same job key and working
directory are deleted once the new one finishes, so the UI never shows two finished runs of one job; a job that
raises (or is terminated) ends its run FAILED. A server's HTTP errors (refused connections, 408, 429, 5xx) are
retried with exponential backoff a bounded number of times (``mlflow.http``); a call that still fails raises
:class:`TrackingError`, naming the server and the call, and the job's result files are kept (``mlflow.unlogged``)
before the job fails. A server that refuses the credentials (401, 403) is not retried:
:class:`TrackingAuthError` names the server and where the credentials came from (the environment or MLflow's
credentials file, never the config), and the job fails at once, its result files kept alike. Tables never read
MLflow: the result files are the source of truth.

The package's modules, one concern each: :mod:`.client` (where runs are logged, retries, :class:`TrackingError`),
:mod:`.store` (the store and its experiments: creation, adoption of a copied store, orphans), :mod:`.runs` (the one
run of a job) and :mod:`.attach` (figures beside their runs). Every public name is importable from the package.
"""
from __future__ import annotations

from dswm.pipeline.tracking.client import (CREDENTIALS_ENV, CREDENTIALS_FILE, HTTP_ENV, MAX_PARAMS_PER_BATCH,
                                           MAX_PARAM_CHARS, REFUSED, TrackingAuthError, TrackingError, client_for,
                                           configure_http, credentials_source, refused_status, retry, sqlite_uri,
                                           tracking_uri, uses_server, workdir_tag)
from dswm.pipeline.tracking.store import (EXPERIMENT_KIND, EXPERIMENT_NOTES, FIGURES_SUFFIX, RUN_KINDS, TREE_TAG,
                                          adopt_store, close_orphans, ensure_store, experiment_of, figures_experiment,
                                          init_store, main_experiment, run_experiments, start_workflow, store_client)
from dswm.pipeline.tracking.runs import JobRun, Terminated, flatten, git_commit, job_run, keep_unlogged
from dswm.pipeline.tracking.attach import attach_figure_outputs, attach_figures

__all__ = ["MAX_PARAMS_PER_BATCH", "MAX_PARAM_CHARS", "HTTP_ENV", "CREDENTIALS_ENV", "CREDENTIALS_FILE", "REFUSED",
           "TrackingError", "TrackingAuthError", "credentials_source", "refused_status", "sqlite_uri", "tracking_uri",
           "uses_server", "configure_http", "client_for", "retry", "workdir_tag", "EXPERIMENT_KIND", "RUN_KINDS",
           "FIGURES_SUFFIX", "EXPERIMENT_NOTES", "figures_experiment", "experiment_of", "init_store", "TREE_TAG",
           "adopt_store", "ensure_store", "store_client", "main_experiment", "run_experiments", "close_orphans",
           "start_workflow", "flatten", "git_commit", "JobRun", "Terminated", "keep_unlogged", "job_run",
           "attach_figures", "attach_figure_outputs"]
