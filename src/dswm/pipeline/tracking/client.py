"""The MLflow client of the ``mlflow`` section: where runs are logged (a SQLite store or a tracking server), the HTTP
retries of a server, and :func:`retry`, through which every tracking call goes (a SQLite lock held by a concurrent job
is waited out; a server that refuses the credentials, 401 or 403, raises :class:`TrackingAuthError` at once; any other
failure raises :class:`TrackingError` naming the store and the call).

A server's credentials never pass through the config: MLflow's client reads them for every request from
``MLFLOW_TRACKING_USERNAME`` / ``MLFLOW_TRACKING_PASSWORD`` or from its credentials file (:data:`CREDENTIALS_FILE`),
and messages name where they came from (:func:`credentials_source`), never what they are."""
from __future__ import annotations

import os
import time
from pathlib import Path
from typing import Any, Mapping

from mlflow.tracking import MlflowClient
from mlflow.utils.credentials import read_mlflow_creds

MAX_PARAMS_PER_BATCH = 100
"""MLflow refuses log_batch requests with more than 100 params."""
MAX_PARAM_CHARS = 6000
"""MLflow's longest param value."""

HTTP_ENV = {"max_retries": "MLFLOW_HTTP_REQUEST_MAX_RETRIES", "backoff_factor": "MLFLOW_HTTP_REQUEST_BACKOFF_FACTOR",
            "timeout_s": "MLFLOW_HTTP_REQUEST_TIMEOUT"}
"""``mlflow.http`` key -> the environment variable through which MLflow's REST client reads it. The client retries
refused connections and the responses 408, 429, 500, 502, 503 and 504 with waits of backoff_factor x 1, 2, 4, ...
seconds (each at most 120 s), at most max_retries times, each request waiting at most timeout_s."""


CREDENTIALS_ENV = ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD")
"""The environment variables from which MLflow's client takes a tracking server's user and password."""
CREDENTIALS_FILE = "~/.mlflow/credentials"
"""MLflow's credentials file (``[mlflow]`` with ``mlflow_tracking_username`` and ``mlflow_tracking_password``),
read for a value the environment does not set."""
REFUSED = (401, 403)
"""The HTTP answers with which a server refuses a request's credentials: never retried (MLflow's client retries only
:data:`HTTP_ENV`'s), the job fails at once."""
INVALID_HOST = "Invalid Host header"
"""The start of a tracking server's 403 answer to a request whose Host header its ``--allowed-hosts`` does not list."""


class TrackingError(RuntimeError):
    """An MLflow call failed for good (after the bounded retries); the message names the store and the call."""


class TrackingAuthError(TrackingError):
    """The tracking server refused the request's credentials (HTTP 401 or 403); not retried. The message names the
    server, the call and where the credentials came from, never the credentials."""


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


def credentials_source() -> str:
    """Where MLflow's client takes a tracking server's credentials from in this process (the names of the environment
    variables or the credentials file), for messages; never the credentials themselves."""
    in_env = [var for var in CREDENTIALS_ENV if os.environ.get(var)]
    read = dict(zip(CREDENTIALS_ENV, read_mlflow_creds()))  # the environment's where set, else the file's
    from_file = [var for var in CREDENTIALS_ENV if var not in in_env and read[var]]
    parts = ([" and ".join(in_env) + " in the environment"] if in_env else []) + \
        ([f"{' and '.join(v.lower() for v in from_file)} of {os.path.expanduser(CREDENTIALS_FILE)}"]
         if from_file else [])
    if not parts:
        return f"none were given ({' and '.join(CREDENTIALS_ENV)} unset, no {CREDENTIALS_FILE})"
    return "they came from " + " and ".join(parts)


def refused_status(err: BaseException) -> int | None:
    """401 or 403 when ``err`` is a tracking server's refusal of the request's credentials (an MLflow exception
    carrying that HTTP status, or a ``requests`` HTTPError with that response), else None."""
    status = None
    if hasattr(err, "get_http_status_code"):
        status = err.get_http_status_code()
    response = getattr(err, "response", None)
    if status not in REFUSED and response is not None:
        status = getattr(response, "status_code", None)
    return status if status in REFUSED else None


def refused_message(uri: str, call: str, status: int, answer: str) -> str:
    """The error of a call that the server at ``uri`` refused with ``status`` (401 or 403); ``answer`` is the
    server's text, read only to tell a refused Host header from refused credentials. Names the server, the call and
    where the credentials came from (:func:`credentials_source`), never the credentials."""
    where = (f"put this server's user and password in {' / '.join(CREDENTIALS_ENV)} or {CREDENTIALS_FILE}, never "
             f"in config.yaml or on a command line (docs/CLUSTER.md)")
    if status == 401:
        return (f"MLflow at {uri}: {call} failed: the server refused the credentials (HTTP 401, not authenticated: "
                f"user or password wrong or missing; {credentials_source()}); not retried: {where}")
    if INVALID_HOST in answer:
        return (f"MLflow at {uri}: {call} failed: the server refused the request's Host header (HTTP 403: the "
                f"server's --allowed-hosts does not list the host and port of mlflow.tracking_uri); not retried")
    return (f"MLflow at {uri}: {call} failed: the server refused the credentials (HTTP 403, permission denied: "
            f"the user may not do this on the experiment; {credentials_source()}); not retried: the server's admin "
            f"grants the user EDIT or MANAGE on the experiment, or {where}")


def concurrent_job_conflict(err: BaseException) -> bool:
    """Whether ``err`` is a conflict with a concurrent job that the same call, made again, gets past:

    * SQLite's lock, held by another job's write (two jobs on two cores);
    * two jobs adding the same new dataset (name and digest) to the experiment at once: MLflow's ``log_inputs``
      looks the dataset up, then inserts it when it was not found, so the slower insert breaks the datasets
      table's unique key (SQLite: "UNIQUE constraint failed", PostgreSQL: "duplicate key value"); made again, the
      call finds the dataset the other job inserted and links the run to it.
    """
    text = str(err)
    if "database is locked" in text:
        return True
    return "INSERT INTO datasets" in text and ("UNIQUE constraint failed" in text or "duplicate key value" in text)


def retry(fn, *args, attempts: int = 8, **kwargs):
    """Call ``fn``, retrying while it meets a concurrent job (:func:`concurrent_job_conflict`).

    A tracking server's transient HTTP errors are retried by MLflow's client itself (:data:`HTTP_ENV`). A server's
    refusal of the credentials (401 or 403) raises :class:`TrackingAuthError` at once. Any other failure, or one that
    outlasts the retries, raises :class:`TrackingError` naming the store and the call.
    """
    for i in range(attempts):
        try:
            return fn(*args, **kwargs)
        except TrackingError:
            raise
        except Exception as err:  # MLflow wraps SQLAlchemy's OperationalError in its own exception types
            if concurrent_job_conflict(err) and i < attempts - 1:
                time.sleep(0.2 * 2**i)
                continue
            uri, call = _describe(fn)
            status = refused_status(err)
            if status is not None:
                raise TrackingAuthError(refused_message(uri, call, status, str(err))) from err
            raise TrackingError(f"MLflow at {uri}: {call} failed: {type(err).__name__}: {err}") from err
    raise AssertionError("unreachable")


def workdir_tag() -> str:
    """The ``workdir`` tag of a run: the working directory its job ran in (the workflow's root, absolute).

    Snakemake's lock keeps two workflows out of one working directory, so a job key is unique within it; on a
    tracking server that several workflows share, the tag keeps each workflow's reruns and orphans its own."""
    return str(Path.cwd().resolve())
