"""The MLflow client of the ``mlflow`` section: where runs are logged (a SQLite store or a tracking server), the HTTP
retries of a server, and :func:`retry`, through which every tracking call goes (a SQLite lock held by a concurrent job
is waited out; any other failure raises :class:`TrackingError` naming the store and the call)."""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping

from mlflow.tracking import MlflowClient

MAX_PARAMS_PER_BATCH = 100
"""MLflow refuses log_batch requests with more than 100 params."""
MAX_PARAM_CHARS = 6000
"""MLflow's longest param value."""

HTTP_ENV = {"max_retries": "MLFLOW_HTTP_REQUEST_MAX_RETRIES", "backoff_factor": "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR",
            "timeout_s": "MLFLOW_HTTP_REQUEST_TIMEOUT"}
"""``mlflow.http`` key -> the environment variable through which MLflow's REST client reads it. The client retries
refused connections and the responses 408, 429, 500, 502, 503 and 504 with waits of backoff_factor x 1, 2, 4, ...
seconds (each at most 120 s), at most max_retries times, each request waiting at most timeout_s."""


class TrackingError(RuntimeError):
    """An MLflow call failed for good (after the bounded retries); the message names the store and the call."""


def sqlite_uri(store: str | Path) -> str:
    """SQLAlchemy URI of the SQLite store at ``store`` (made absolute, so jobs agree from any cwd)."""
    return "sqlite:///" + str(Path(store).resolve())


def tracking_uri(mlflow_cfg: Mapping[str, Any]) -> str:
    """Where the runs of ``mlflow_cfg`` (the ``mlflow`` section) are logged: its ``tracking_uri`` (a tracking server)
    when set, else the SQLite store ``store``."""
    return mlflow_cfg.get("tracking_uri") or sqlite_uri(mlflow_cfg["store"])


def uses_server(mlflow_cfg: Mapping[str, Any]) -> bool:
    """True when ``mlflow_cfg`` names a tracking server instead of the SQLite store."""
    return bool(mlflow_cfg.get("tracking_uri"))


def configure_http(http: Mapping[str, Any] | None) -> None:
    """Set MLflow's HTTP retry, backoff and timeout for this process from ``mlflow.http`` (:data:`HTTP_ENV`)."""
    for key, var in HTTP_ENV.items():
        if http and http.get(key) is not None:
            os.environ[var] = str(int(http[key]))


def client_for(mlflow_cfg: Mapping[str, Any]) -> MlflowClient:
    """The MLflow client of ``mlflow_cfg``, with its HTTP retries configured (:func:`configure_http`)."""
    configure_http(mlflow_cfg.get("http"))
    return MlflowClient(tracking_uri=tracking_uri(mlflow_cfg))


def _describe(fn) -> tuple[str, str]:
    """(store, call) of an MLflow client method, for error messages."""
    owner = getattr(fn, "__self__", None)
    uri = getattr(owner, "_tracking_client", None)
    uri = getattr(uri, "tracking_uri", None) or "the MLflow store"
    return str(uri), getattr(fn, "__name__", "call")


def retry(fn, *args, attempts: int = 8, **kwargs):
    """Call ``fn``, retrying while SQLite reports a lock held by a concurrent job (two jobs on two cores).

    A tracking server's transient HTTP errors are retried by MLflow's client itself (:data:`HTTP_ENV`). Any other
    failure, or one that outlasts the retries, raises :class:`TrackingError` naming the store and the call.
    """
    for i in range(attempts):
        try:
            return fn(*args, **kwargs)
        except TrackingError:
            raise
        except Exception as err:  # MLflow wraps SQLAlchemy's OperationalError in its own exception types
            if "database is locked" in str(err) and i < attempts - 1:
                time.sleep(0.2 * 2**i)
                continue
            uri, call = _describe(fn)
            raise TrackingError(f"MLflow at {uri}: {call} failed: {type(err).__name__}: {err}") from err
    raise AssertionError("unreachable")


def workdir_tag() -> str:
    """The ``workdir`` tag of a run: the working directory its job ran in (the workflow's root, absolute).

    Snakemake's lock keeps two workflows out of one working directory, so a job key is unique within it; on a
    tracking server that several workflows share, the tag keeps each workflow's reruns and orphans its own."""
    return str(Path.cwd().resolve())
