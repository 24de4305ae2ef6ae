"""MLflow tracking: store and experiment, one run per job, batches, no duplicate FINISHED runs, FAILED runs."""
import os

import pytest
from mlflow.tracking import MlflowClient

from conftest import HTTP_ENV_PREFIX
from dswm.pipeline import tracking

RESOLVED = {"profile": "smoke", "scenario": {"n_uavs": 16, "channel": {"a": 9.61}},
            "methods": {"run": ["static", "greedy"]}, "mlflow": {}}


@pytest.fixture(scope="module")
def db(tmp_path_factory):
    """One SQLite store for the module (creating its tables takes seconds); each test has its experiment."""
    return tmp_path_factory.mktemp("mlflow") / "results" / "mlflow.db"


@pytest.fixture
def store(db, tmp_path, request):
    cfg = {"store": str(db), "artifacts": str(tmp_path / "mlartifacts"), "experiment": request.node.name,
           "batch_size": 7}
    info = tracking.init_store(store=cfg["store"], artifacts=cfg["artifacts"], experiment=cfg["experiment"])
    return cfg, info, MlflowClient(tracking_uri=info["tracking_uri"])


def runs(client, info, status=None):
    q = f"attributes.status = '{status}'" if status else ""
    return client.search_runs([info["experiment_id"]], filter_string=q)


def open_job(cfg, tmp_path, **kw):
    args = dict(mlflow_cfg=cfg, settings=RESOLVED, stage="evaluate", dataset="milan", method="static", seed=0,
                config_hash="abc123", repo=tmp_path)
    args.update(kw)
    return tracking.job_run(**args)


def test_init_creates_the_store_and_the_experiment_once(store, db, tmp_path):
    cfg, info, client = store
    assert db.is_file() and client.get_experiment_by_name(cfg["experiment"]).experiment_id == info["experiment_id"]
    again = tracking.init_store(store=cfg["store"], artifacts=cfg["artifacts"], experiment=cfg["experiment"])
    assert again["experiment_id"] == info["experiment_id"]
    assert info["artifact_location"] == (tmp_path / "mlartifacts").resolve().as_uri()


def test_the_experiment_opens_on_the_runs_view_and_a_run_records_its_demand_tensor(store, tmp_path):
    cfg, info, client = store
    assert client.get_experiment(info["experiment_id"]).tags["mlflow.experimentKind"] == "custom_model_development"
    tensor = tmp_path / "data" / "milan"
    tensor.mkdir(parents=True)
    (tensor / "demand.parquet").write_bytes(b"demand of milan")
    from hashlib import sha256

    from dswm.pipeline.setup import log_demand_input

    with open_job(cfg, tmp_path) as run:
        full = log_demand_input(run, tensor, "milan", "evaluation")
    assert full == sha256(b"demand of milan").hexdigest()
    (r,) = runs(client, info)
    (entry,) = r.inputs.dataset_inputs
    assert (entry.dataset.name, entry.dataset.digest) == ("milan", full[:16])
    assert (tensor / "demand.parquet").resolve().as_uri() in entry.dataset.source
    assert [(t.key, t.value) for t in entry.tags] == [("mlflow.data.context", "evaluation")]


def test_a_job_run_has_tags_params_batched_metrics_and_artifacts(store, tmp_path):
    cfg, info, client = store
    result = tmp_path / "days.parquet"
    result.write_bytes(b"not really parquet")
    with open_job(cfg, tmp_path) as run:
        for day in range(10):  # 20 values with batch_size 7: sent as 7 + 7 + 6
            run.log_metrics({"day/sr_mean": 0.5 + day / 100, "day/jain": 1.0}, step=day)
        run.log_series("losses/total", [3.0, 2.0, 1.0], steps=[10, 20, 30])
        run.log_artifact(result)
    (r,) = runs(client, info)
    assert r.info.status == "FINISHED"
    tags = r.data.tags
    assert (tags["dataset"], tags["method"], tags["seed"], tags["profile"], tags["config_hash"]) == \
        ("milan", "static", "0", "smoke", "abc123")
    assert tags["job_key"] == "evaluate/milan/static/seed0" and tags["git_commit"] == "unknown"
    assert r.data.params["scenario.channel.a"] == "9.61" and r.data.params["methods.run"] == '["static", "greedy"]'
    hist = client.get_metric_history(r.info.run_id, "day/sr_mean")
    assert sorted((m.step, round(m.value, 6)) for m in hist) == [(d, round(0.5 + d / 100, 6)) for d in range(10)]
    assert [(m.step, m.value) for m in client.get_metric_history(r.info.run_id, "losses/total")] == \
        [(10, 3.0), (20, 2.0), (30, 1.0)]
    assert [a.path for a in client.list_artifacts(r.info.run_id)] == ["days.parquet"]


def test_a_rerun_leaves_one_finished_run_per_job(store, tmp_path):
    cfg, info, client = store
    for _ in range(3):
        with open_job(cfg, tmp_path) as run:
            run.log_metrics({"id/sr_mean": 0.7})
    with open_job(cfg, tmp_path, seed=1):
        pass
    finished = runs(client, info, "FINISHED")
    assert sorted(r.data.tags["job_key"] for r in finished) == ["evaluate/milan/static/seed0",
                                                                "evaluate/milan/static/seed1"]
    assert run.run_id in {r.info.run_id for r in finished}  # the latest run of the job is the one kept


def test_a_failing_job_ends_failed_and_a_killed_one_is_marked_killed(store, tmp_path):
    cfg, info, client = store
    with pytest.raises(RuntimeError, match="boom"):
        with open_job(cfg, tmp_path) as run:
            run.log_metrics({"day/sr_mean": 0.1}, step=0)
            raise RuntimeError("boom")
    assert client.get_run(run.run_id).info.status == "FAILED"
    # a run left RUNNING (job killed with SIGKILL) is closed as KILLED when the job runs again
    exp = info["experiment_id"]
    stale = client.create_run(exp, tags={"job_key": "evaluate/milan/static/seed0", "workdir": tracking.workdir_tag()})
    with open_job(cfg, tmp_path):
        pass
    assert client.get_run(stale.info.run_id).info.status == "KILLED"
    assert client.get_run(run.run_id).info.status == "FAILED"  # failed runs are kept as history


def test_an_interruption_while_the_run_is_set_up_ends_it_failed(store, tmp_path, monkeypatch):
    """A Ctrl-C while the params are logged (before the job body) leaves no run RUNNING."""
    cfg, info, client = store
    real = MlflowClient.log_batch

    def interrupted(self, run_id, metrics=(), params=(), tags=()):
        if params:
            raise KeyboardInterrupt
        return real(self, run_id, metrics=metrics, params=params, tags=tags)

    monkeypatch.setattr(MlflowClient, "log_batch", interrupted)
    with pytest.raises(KeyboardInterrupt):
        with open_job(cfg, tmp_path):
            raise AssertionError("the body must not run")
    (only,) = runs(client, info)
    assert only.info.status == "FAILED"


def test_a_sigterm_as_the_run_is_created_ends_it_failed(store, tmp_path, monkeypatch):
    """SIGTERM delivered right after MLflow created the run (before the job holds its id) still ends it FAILED."""
    import os
    import signal

    cfg, info, client = store
    real = MlflowClient.create_run

    def create_then_term(self, *args, **kwargs):
        run = real(self, *args, **kwargs)
        os.kill(os.getpid(), signal.SIGTERM)  # noted, and raised once the run id is bound
        return run

    monkeypatch.setattr(MlflowClient, "create_run", create_then_term)
    before = (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT))
    with pytest.raises(tracking.Terminated, match="terminated by signal 15"):
        with open_job(cfg, tmp_path):
            raise AssertionError("the body must not run")
    (only,) = runs(client, info)
    assert only.info.status == "FAILED"
    assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before  # handlers restored


def test_a_workflow_start_closes_runs_a_sigkill_left_running(store, tmp_path):
    cfg, info, client = store
    exp = info["experiment_id"]
    here = tracking.workdir_tag()
    orphans = [client.create_run(exp, tags={"job_key": f"train/milan/dswm/seed{s}", "workdir": here}) for s in (0, 1)]
    # a run of another working directory sharing the store (a tracking server) belongs to a live workflow there
    elsewhere = client.create_run(exp, tags={"job_key": "train/milan/dswm/seed0", "workdir": "/other/checkout"})
    with open_job(cfg, tmp_path):
        pass
    assert tracking.close_orphans(mlflow_cfg=cfg) == 2
    assert [client.get_run(r.info.run_id).info.status for r in orphans] == ["KILLED", "KILLED"]
    assert client.get_run(elsewhere.info.run_id).info.status == "RUNNING"
    assert [r.info.status for r in runs(client, info, "FINISHED")] == ["FINISHED"]  # a finished run is kept
    assert tracking.close_orphans(mlflow_cfg=cfg) == 0
    assert tracking.close_orphans(mlflow_cfg={"store": str(tmp_path / "absent.db"), "experiment": "x"}) == 0


def test_missing_store_is_reported_with_the_rule_that_creates_it(tmp_path):
    cfg = {"store": str(tmp_path / "none.db"), "artifacts": str(tmp_path), "experiment": "x", "batch_size": 10}
    with pytest.raises(FileNotFoundError, match="mlflow_init"):
        with open_job(cfg, tmp_path):
            pass


def test_flatten_gives_dotted_string_params():
    flat = tracking.flatten({"a": {"b": 1, "c": [1, 2], "d": {}}, "e": None})
    assert flat == {"a.b": "1", "a.c": "[1, 2]", "a.d": "{}", "e": "None"}


def test_a_rerun_replaces_only_the_runs_of_its_own_working_directory(store, tmp_path):
    """Two checkouts logging to one tracking server: a job's rerun in one leaves the other's finished run."""
    cfg, info, client = store
    other = client.create_run(info["experiment_id"], tags={"job_key": "evaluate/milan/static/seed0",
                                                           "workdir": "/other/checkout"})
    client.set_terminated(other.info.run_id, "FINISHED")
    for _ in range(2):
        with open_job(cfg, tmp_path) as run:
            pass
    finished = {r.info.run_id: r.data.tags["workdir"] for r in runs(client, info, "FINISHED")}
    assert finished == {other.info.run_id: "/other/checkout", run.run_id: tracking.workdir_tag()}


def test_a_tracking_failure_mid_job_keeps_the_result_files_and_names_them(store, tmp_path, monkeypatch):
    """The store refuses the artifact upload: the job fails with the store and the call named, its run ends
    FAILED, and the result files it wrote are copied where Snakemake's clean-up of a failed job cannot reach."""
    from mlflow.exceptions import MlflowException

    cfg, info, client = store
    cfg = {**cfg, "unlogged": str(tmp_path / "unlogged")}
    days = tmp_path / "out" / "days.parquet"
    traj = tmp_path / "out" / "trajectory.npz"

    def log_artifact(self, run_id, local_path, artifact_path=None):
        raise MlflowException("503 Service Unavailable")

    monkeypatch.setattr(MlflowClient, "log_artifact", log_artifact)
    with pytest.raises(tracking.TrackingError) as err:
        with open_job(cfg, tmp_path, keep=[days, traj]) as run:
            days.parent.mkdir()
            days.write_bytes(b"the day results")
            run.log_artifact(days)
    message = str(err.value)
    kept = tmp_path / "unlogged" / "evaluate" / "milan" / "static" / "seed0"
    assert "job evaluate/milan/static/seed0" in message and "log_artifact failed" in message
    assert info["tracking_uri"] in message and "503 Service Unavailable" in message
    assert f"kept in {kept}: days.parquet" in message
    assert (kept / "days.parquet").read_bytes() == b"the day results" and not (kept / "trajectory.npz").exists()
    assert client.get_run(run.run_id).info.status == "FAILED"


class _Unavailable:
    """An HTTP server on a loopback port that answers every request ``status`` (503 by default) with ``body`` and
    counts the requests, keeping each one's Authorization header."""

    def __init__(self, status: int = 503, body: bytes = b""):
        import http.server
        import threading

        hits = self.hits = []
        self.auth = []
        auth = self.auth

        class Handler(http.server.BaseHTTPRequestHandler):
            def _answer(self):
                hits.append(self.path)
                auth.append(self.headers.get("Authorization"))
                self.send_response(status)
                self.send_header("Content-Type", "text/plain")
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

            do_GET = do_POST = do_PATCH = do_DELETE = _answer

            def log_message(self, *args):
                pass

        self.server = http.server.ThreadingHTTPServer(("127.0.0.1", 0), Handler)
        self.url = f"http://127.0.0.1:{self.server.server_address[1]}"
        self.thread = threading.Thread(target=self.server.serve_forever, daemon=True)
        self.thread.start()

    def close(self):
        self.server.shutdown()
        self.server.server_close()


@pytest.fixture
def unavailable():
    server = _Unavailable()
    yield server
    server.close()


def test_a_job_sets_mlflow_s_http_variables_which_the_test_fixture_restores(tmp_path):
    """configure_http writes MLflow's HTTP variables into the process's environment; conftest's
    mlflow_http_env_restored undoes every variable with its prefix after each test, so each of them must carry it."""
    tracking.configure_http({"max_retries": 2, "backoff_factor": 0, "timeout_s": 5})
    written = {var: os.environ[var] for var in tracking.HTTP_ENV.values()}
    assert sorted(written.values()) == ["0", "2", "5"]
    assert [var for var in written if not var.startswith(HTTP_ENV_PREFIX)] == []


def test_a_server_that_answers_503_is_retried_a_bounded_number_of_times_then_named(unavailable, tmp_path,
                                                                                    monkeypatch):
    for var in tracking.HTTP_ENV.values():
        monkeypatch.delenv(var, raising=False)
    cfg = {"tracking_uri": unavailable.url, "store": str(tmp_path / "unused.db"), "artifacts": str(tmp_path / "a"),
           "experiment": "x", "batch_size": 10, "http": {"max_retries": 2, "backoff_factor": 0, "timeout_s": 5},
           "unlogged": str(tmp_path / "unlogged")}
    with pytest.raises(tracking.TrackingError) as err:
        with open_job(cfg, tmp_path, keep=[tmp_path / "days.parquet"]):
            raise AssertionError("the body must not run")
    assert len(unavailable.hits) == 3  # one request and its 2 retries, then the job fails
    message = str(err.value)
    assert unavailable.url in message and "get_experiment_by_name failed" in message
    assert "nothing was computed" in message and not (tmp_path / "unlogged").exists()
    with pytest.raises(tracking.TrackingError, match=unavailable.url):
        tracking.init_store(store=cfg["store"], artifacts=cfg["artifacts"], experiment="x",
                            tracking_uri=unavailable.url, http={"max_retries": 0, "backoff_factor": 0, "timeout_s": 5})
    assert len(unavailable.hits) == 4 and not (tmp_path / "unused.db").exists()


# ---------------------------------------------------------------------------- a server that refuses the credentials

NOT_AUTHENTICATED = (b"You are not authenticated. Please see https://www.mlflow.org/docs/latest/auth/index.html"
                     b"#authenticating-to-mlflow on how to authenticate.")
"""The answer of MLflow's basic-auth app to a request without valid credentials (HTTP 401)."""
USER, PASSWORD = "writer", "a-password-of-the-writer-42"


@pytest.fixture
def credentials(monkeypatch, tmp_path):
    """The writer's credentials in the environment, no credentials file (HOME is an empty directory), MLflow's own
    HTTP settings unset."""
    monkeypatch.setenv("HOME", str(tmp_path / "home"))
    monkeypatch.setenv("MLFLOW_TRACKING_USERNAME", USER)
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", PASSWORD)
    for var in tracking.HTTP_ENV.values():
        monkeypatch.delenv(var, raising=False)


def _server_cfg(url, tmp_path):
    """The mlflow section of a job logging to the server at ``url``, with 5 retries: a refusal must use none."""
    return {"tracking_uri": url, "store": str(tmp_path / "unused.db"), "artifacts": str(tmp_path / "a"),
            "experiment": "x", "batch_size": 10, "http": {"max_retries": 5, "backoff_factor": 1, "timeout_s": 5},
            "unlogged": str(tmp_path / "unlogged")}


@pytest.mark.parametrize("status, body, said", [
    (401, NOT_AUTHENTICATED, "the server refused the credentials (HTTP 401, not authenticated: user or password "
                             "wrong or missing; they came from MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD "
                             "in the environment); not retried: put this server's user and password in "
                             "MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD or ~/.mlflow/credentials, never in "
                             "config.yaml or on a command line (docs/CLUSTER.md)"),
    (403, b"Permission denied", "the server refused the credentials (HTTP 403, permission denied: the user may not do "
                                "this on the experiment; they came from MLFLOW_TRACKING_USERNAME and "
                                "MLFLOW_TRACKING_PASSWORD in the environment); not retried: the server's admin grants "
                                "the user EDIT or MANAGE on the experiment, or put this server's user and password "
                                "in MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD or ~/.mlflow/credentials, "
                                "never in config.yaml or on a command line (docs/CLUSTER.md)"),
])
def test_a_server_that_refuses_the_credentials_is_asked_once_and_the_job_fails_at_once(credentials, tmp_path,
                                                                                      status, body, said):
    import base64

    server = _Unavailable(status, body)
    try:
        cfg = _server_cfg(server.url, tmp_path)
        with pytest.raises(tracking.TrackingAuthError) as err:
            with open_job(cfg, tmp_path, keep=[tmp_path / "days.parquet"]):
                raise AssertionError("the body must not run")
    finally:
        server.close()
    # one request, with the writer's credentials, and no retry although mlflow.http allows 5 (with backoff 1 s)
    assert server.hits == ["/api/2.0/mlflow/experiments/get-by-name?experiment_name=x"]
    assert server.auth == ["Basic " + base64.b64encode(f"{USER}:{PASSWORD}".encode()).decode()]
    message = str(err.value)
    assert message == (f"job evaluate/milan/static/seed0: MLflow at {server.url}: get_experiment_by_name failed: "
                       f"{said}; nothing was computed, run the job again with credentials the server accepts")
    assert PASSWORD not in message and USER not in message
    assert not (tmp_path / "unlogged").exists()


def test_a_403_for_the_host_header_names_allowed_hosts_not_the_credentials(credentials, tmp_path):
    server = _Unavailable(403, b"Invalid Host header - possible DNS rebinding attack detected")
    try:
        with pytest.raises(tracking.TrackingAuthError) as err:
            tracking.init_store(store=tmp_path / "unused.db", artifacts=tmp_path / "a", experiment="x",
                                tracking_uri=server.url, http={"max_retries": 5, "backoff_factor": 1, "timeout_s": 5})
    finally:
        server.close()
    assert len(server.hits) == 1
    assert str(err.value) == (f"MLflow at {server.url}: get_experiment_by_name failed: the server refused the "
                              f"request's Host header (HTTP 403: the server's --allowed-hosts does not list the host "
                              f"and port of mlflow.tracking_uri); not retried")


def test_credentials_refused_mid_job_keep_the_result_files_and_name_them(store, credentials, tmp_path, monkeypatch):
    """The server stops accepting the job's credentials after the run started (its password changed, its user
    removed): the job fails at that call, with the server's refusal named, and keeps its result files."""
    from mlflow.exceptions import MlflowException
    from mlflow.protos.databricks_pb2 import UNAUTHENTICATED

    cfg, info, client = store
    cfg = {**cfg, "unlogged": str(tmp_path / "unlogged")}
    days = tmp_path / "out" / "days.parquet"
    calls = []

    def log_artifact(self, run_id, local_path, artifact_path=None):  # what MLflow's REST client raises on a 401
        calls.append(local_path)
        raise MlflowException("API request to endpoint /api/2.0/mlflow/runs/log-artifact failed with error code 401 "
                              f"!= 200. Response body: '{NOT_AUTHENTICATED.decode()}'", error_code=UNAUTHENTICATED)

    monkeypatch.setattr(MlflowClient, "log_artifact", log_artifact)
    with pytest.raises(tracking.TrackingAuthError) as err:
        with open_job(cfg, tmp_path, keep=[days]) as run:
            days.parent.mkdir()
            days.write_bytes(b"the day results")
            run.log_artifact(days)
    kept = tmp_path / "unlogged" / "evaluate" / "milan" / "static" / "seed0"
    assert str(err.value) == (
        f"job evaluate/milan/static/seed0: MLflow at {info['tracking_uri']}: log_artifact failed: the server refused "
        f"the credentials (HTTP 401, not authenticated: user or password wrong or missing; they came from "
        f"MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD in the environment); not retried: put this server's "
        f"user and password in MLFLOW_TRACKING_USERNAME / MLFLOW_TRACKING_PASSWORD or ~/.mlflow/credentials, never "
        f"in config.yaml or on a command line (docs/CLUSTER.md); the job fails, its result files are kept in "
        f"{kept}: days.parquet")
    assert len(calls) == 1 and (kept / "days.parquet").read_bytes() == b"the day results"
    assert client.get_run(run.run_id).info.status == "FAILED"


def test_the_source_of_the_credentials_is_named_never_their_value(monkeypatch, tmp_path):
    home = tmp_path / "home"
    monkeypatch.setenv("HOME", str(home))
    monkeypatch.delenv("MLFLOW_TRACKING_USERNAME", raising=False)
    monkeypatch.delenv("MLFLOW_TRACKING_PASSWORD", raising=False)
    assert tracking.credentials_source() == ("none were given (MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD "
                                             "unset, no ~/.mlflow/credentials)")
    (home / ".mlflow").mkdir(parents=True)
    (home / ".mlflow" / "credentials").write_text(f"[mlflow]\nmlflow_tracking_username = {USER}\n"
                                                  f"mlflow_tracking_password = {PASSWORD}\n")
    assert tracking.credentials_source() == (f"they came from mlflow_tracking_username and mlflow_tracking_password of "
                                             f"{home}/.mlflow/credentials")
    monkeypatch.setenv("MLFLOW_TRACKING_PASSWORD", "another-password-123")
    assert tracking.credentials_source() == (f"they came from MLFLOW_TRACKING_PASSWORD in the environment and "
                                             f"mlflow_tracking_username of {home}/.mlflow/credentials")


# ---------------------------------------------------------------------------- a tree copied with its store

TREE_CFG = {"store": "results/mlflow.db", "artifacts": "results/mlartifacts", "experiment": "dswm", "batch_size": 10}


def _files(root):
    """{relative path: bytes} of every file under ``root``."""
    return {str(p.relative_to(root)): p.read_bytes() for p in sorted(root.rglob("*")) if p.is_file()}


def _evaluate(tree, days: bytes):
    """One evaluate job of the workflow in ``tree`` (its working directory): a result file logged as artifact."""
    result = tree / "results" / "milan" / "static" / "seed0" / "days.parquet"
    result.parent.mkdir(parents=True, exist_ok=True)
    result.write_bytes(days)
    with open_job(TREE_CFG, tree) as run:
        run.log_metrics({"id/sr_mean": 0.7})
        run.log_artifact(result)
    return run


def test_a_copied_tree_logs_into_itself_and_leaves_the_original_alone(tmp_path, monkeypatch):
    """The issue's case: a complete tree copied like `cp -a`, a job rerun in the copy (paths with a space: file URIs
    quote it)."""
    import hashlib
    import shutil

    original, copy = tmp_path / "a run", tmp_path / "a run-copy"
    original.mkdir()
    monkeypatch.chdir(original)
    tracking.init_store(store=TREE_CFG["store"], artifacts=TREE_CFG["artifacts"], experiment="dswm")
    first = _evaluate(original, b"days of the original")
    shutil.copytree(original, copy, symlinks=True)  # cp -a: links kept, file times and modes copied
    before = _files(original / "results" / "mlartifacts")
    store_sha = hashlib.sha256((original / "results" / "mlflow.db").read_bytes()).hexdigest()

    monkeypatch.chdir(copy)
    rerun = _evaluate(copy, b"days of the copy")

    client = MlflowClient(tracking_uri=tracking.sqlite_uri(copy / "results" / "mlflow.db"))
    exp = client.get_experiment_by_name("dswm")
    assert exp.artifact_location == (copy / "results" / "mlartifacts").as_uri()
    assert exp.tags[tracking.TREE_TAG] == str(copy)
    figures = client.get_experiment_by_name(tracking.figures_experiment("dswm"))  # the figures' runs move alike
    assert figures.artifact_location == exp.artifact_location and figures.tags[tracking.TREE_TAG] == str(copy)
    assert (copy / "results" / "mlartifacts" / rerun.run_id / "artifacts" / "days.parquet").read_bytes() == \
        b"days of the copy"
    assert _files(original / "results" / "mlartifacts") == before  # nothing written into the original
    assert hashlib.sha256((original / "results" / "mlflow.db").read_bytes()).hexdigest() == store_sha
    # the copy's store shows one current run of the job: the inherited FINISHED run is replaced by the rerun
    finished = client.search_runs([exp.experiment_id], filter_string="attributes.status = 'FINISHED'")
    assert [r.info.run_id for r in finished] == [rerun.run_id]
    inherited = client.get_run(first.run_id)
    assert inherited.info.lifecycle_stage == "deleted" and inherited.data.tags["workdir"] == str(copy)
    assert inherited.info.artifact_uri == (copy / "results" / "mlartifacts" / first.run_id / "artifacts").as_uri()
    # the original's store still names its own tree only
    orig = MlflowClient(tracking_uri=tracking.sqlite_uri(original / "results" / "mlflow.db"))
    assert orig.get_experiment_by_name("dswm").artifact_location == (original / "results" / "mlartifacts").as_uri()
    assert [r.info.run_id for r in orig.search_runs([exp.experiment_id])] == [first.run_id]


@pytest.mark.parametrize("tagged", [True, False], ids=["store", "store_made_before_the_tree_tag"])
def test_a_workflow_start_in_a_copy_adopts_the_store_and_says_so(tmp_path, monkeypatch, tagged):
    """`onstart`: the copy's store is made its own before any job; a second start finds nothing to do. A store
    without the tree tag (made before it existed) is known by its artifact location."""
    import shutil
    import sqlite3

    original, copy = tmp_path / "a run", tmp_path / "a run-copy"
    original.mkdir()
    monkeypatch.chdir(original)
    tracking.init_store(store=TREE_CFG["store"], artifacts=TREE_CFG["artifacts"], experiment="dswm")
    _evaluate(original, b"days")
    assert tracking.start_workflow(TREE_CFG) == []  # the original is its store's tree
    if not tagged:
        with sqlite3.connect(original / "results" / "mlflow.db") as db:
            db.execute("DELETE FROM experiment_tags WHERE key = ?", (tracking.TREE_TAG,))
    shutil.copytree(original, copy, symlinks=True)
    monkeypatch.chdir(copy)
    old, new = (original / "results" / "mlartifacts").as_uri(), (copy / "results" / "mlartifacts").as_uri()
    assert tracking.start_workflow(TREE_CFG) == [
        f"the store's artifacts now go under {new} (it named {old}); 1 run(s) of {original} (the tree it was "
        f"copied from) are this tree's"]
    assert tracking.start_workflow(TREE_CFG) == []
    client = MlflowClient(tracking_uri=tracking.sqlite_uri(copy / "results" / "mlflow.db"))
    (run,) = client.search_runs([client.get_experiment_by_name("dswm").experiment_id])
    assert run.data.tags["workdir"] == str(copy) and run.info.artifact_uri.startswith(new + "/")
    # a tracking server keeps its own artifact location: nothing of the store is touched
    assert tracking.adopt_store({**TREE_CFG, "tracking_uri": "http://127.0.0.1:1"}) is None


def test_each_kind_of_run_is_tagged_and_the_figures_runs_have_their_own_experiment(store, tmp_path):
    """The tables' runs (kind main) are alone in the configured experiment, which the UI opens on; the extra,
    probe, world-model quality and learning-curve runs (each tagged with its kind) go to `<experiment>-figures`,
    which mlflow_init creates and describes beside it."""
    cfg, info, client = store
    main = client.get_experiment(info["experiment_id"])
    figures = client.get_experiment_by_name(cfg["experiment"] + "-figures")
    assert info["figures_experiment"] == figures.name and info["figures_experiment_id"] == figures.experiment_id
    assert figures.tags["mlflow.experimentKind"] == "custom_model_development"
    assert figures.artifact_location == main.artifact_location
    assert main.tags["mlflow.note.content"] == (
        f"The runs of the tables: one train or evaluate run per job (tag kind = main). The runs behind the figures "
        f"only are in the experiment '{figures.name}'.")
    assert f"The tables' runs are in the experiment '{main.name}'." in figures.tags["mlflow.note.content"]
    jobs = [("train", "main"), ("evaluate", "main"), ("extra/K8/evaluate", "extra"), ("probe", "probe"),
            ("wm", "wm_quality"), ("learning/train", "learning")]
    for stage, kind in jobs:
        with open_job(cfg, tmp_path, stage=stage, kind=kind):
            pass
    where = {e: sorted((r.data.tags["stage"], r.data.tags["kind"]) for r in client.search_runs([e]))
             for e in (main.experiment_id, figures.experiment_id)}
    assert where == {main.experiment_id: [("evaluate", "main"), ("train", "main")],
                     figures.experiment_id: [("extra/K8/evaluate", "extra"), ("learning/train", "learning"),
                                             ("probe", "probe"), ("wm", "wm_quality")]}
    with pytest.raises(ValueError, match="run kind 'figure': expected one of main, extra, probe, wm_quality, "
                                         "learning"):
        tracking.experiment_of(cfg, "figure")


def test_a_store_made_before_the_figures_experiment_gets_it_and_loses_no_run(db, tmp_path, request):
    """A store whose mlflow_init ran before the figures' runs had their own experiment (the main one alone, every
    run in it): the first such job creates it, its rerun replaces the earlier run it had left in the main
    experiment, a figure attaches to runs of both, and a workflow start closes orphans in both."""
    cfg = {"store": str(db), "artifacts": str(tmp_path / "mlartifacts"), "experiment": request.node.name,
           "batch_size": 7}
    client = MlflowClient(tracking_uri=tracking.sqlite_uri(db))
    main_id = client.create_experiment(cfg["experiment"], artifact_location=(tmp_path / "mlartifacts").as_uri())
    assert client.get_experiment_by_name(cfg["experiment"] + "-figures") is None
    here = tracking.workdir_tag()
    old = client.create_run(main_id, tags={"job_key": "probe/milan/dswm/seed0", "workdir": here,
                                                         "stage": "probe"})
    client.set_terminated(old.info.run_id, "FINISHED")
    with open_job(cfg, tmp_path, stage="probe", method="dswm", kind="probe") as run:
        pass
    figures = client.get_experiment_by_name(cfg["experiment"] + "-figures")
    assert figures.artifact_location == (tmp_path / "mlartifacts").as_uri()
    assert figures.tags["mlflow.experimentKind"] == "custom_model_development"
    assert figures.tags["mlflow.note.content"].startswith("The runs behind the figures only")
    assert client.get_run(run.run_id).info.experiment_id == figures.experiment_id
    assert client.get_run(old.info.run_id).info.lifecycle_stage == "deleted"
    with open_job(cfg, tmp_path, stage="evaluate", method="dswm"):
        pass
    png = tmp_path / "fig.png"
    png.write_bytes(b"png")
    assert tracking.attach_figures(mlflow_cfg=cfg, paths=[png], stage=["evaluate", "probe"], methods=["dswm"]) == 2
    orphan = client.create_run(figures.experiment_id, tags={"job_key": "wm/milan/dswm/seed0", "workdir": here})
    assert tracking.close_orphans(mlflow_cfg=cfg) == 1
    assert client.get_run(orphan.info.run_id).info.status == "KILLED"


def _log_same_datasets(cfg, tmp_path, seed, barrier, rounds, errors):
    """One job's side of the race below: a run, then ``rounds`` datasets logged as the other job logs them."""
    try:
        path = tmp_path / "demand.parquet"
        with open_job(cfg, tmp_path, seed=seed) as run:
            for i in range(rounds):
                barrier.wait(timeout=60)
                run.log_dataset(path, name="milan", digest=f"digest{i:04d}", context="training")
    except Exception as err:  # the parent names it
        errors.put(f"seed {seed}: {type(err).__name__}: {err}"[:400])


def test_two_jobs_logging_the_same_new_dataset_at_once_both_get_it(store, tmp_path):
    """MLflow's log_inputs looks a dataset up, then inserts it: two jobs that add the same new dataset at the same
    moment (two train jobs of one dataset on two cores) race for its unique key, and the loser is retried, finding
    the winner's row (``tracking.concurrent_job_conflict``), instead of failing its job."""
    import multiprocessing

    cfg, info, client = store
    (tmp_path / "demand.parquet").write_bytes(b"demand")
    rounds = 25
    ctx = multiprocessing.get_context("fork")
    barrier, errors = ctx.Barrier(2), ctx.Queue()
    jobs = [ctx.Process(target=_log_same_datasets, args=(cfg, tmp_path, seed, barrier, rounds, errors))
            for seed in (0, 1)]
    for job in jobs:
        job.start()
    for job in jobs:
        job.join(timeout=300)
    failures = [errors.get() for _ in range(errors.qsize())]
    assert failures == [] and [job.exitcode for job in jobs] == [0, 0]
    finished = runs(client, info, "FINISHED")
    assert len(finished) == 2
    for r in finished:  # each run holds every dataset once, the same rows as the other run's
        assert sorted(d.dataset.digest for d in r.inputs.dataset_inputs) == [f"digest{i:04d}" for i in range(rounds)]


def test_only_a_conflict_with_a_concurrent_job_is_retried():
    race = ("(sqlite3.IntegrityError) UNIQUE constraint failed: datasets.experiment_id, datasets.name, "
            "datasets.digest [SQL: INSERT INTO datasets (dataset_uuid, experiment_id, name, digest) VALUES (?, ?, ?, ?)]")
    assert tracking.client.concurrent_job_conflict(RuntimeError(race))
    assert tracking.client.concurrent_job_conflict(RuntimeError(
        'duplicate key value violates unique constraint "dataset_pk" [SQL: INSERT INTO datasets (dataset_uuid) ...]'))
    assert tracking.client.concurrent_job_conflict(RuntimeError("(sqlite3.OperationalError) database is locked"))
    assert not tracking.client.concurrent_job_conflict(RuntimeError(
        "(sqlite3.IntegrityError) UNIQUE constraint failed: params.key, params.run_uuid [SQL: INSERT INTO params]"))
    calls = []

    def flaky():
        calls.append(1)
        if len(calls) == 1:
            raise RuntimeError(race)
        return "linked"

    assert tracking.retry(flaky) == "linked" and len(calls) == 2

    def duplicate_param():
        raise RuntimeError("(sqlite3.IntegrityError) UNIQUE constraint failed: params.key [SQL: INSERT INTO params]")

    with pytest.raises(tracking.TrackingError, match="UNIQUE constraint failed: params.key"):
        tracking.retry(duplicate_param)
