"""The workflow on real cluster engines, started on loopback (tests/cluster/engines.py): the smoke DAG of Milan through
Snakemake's SLURM executor (`--executor slurm --profile profiles/slurm --jobs 4`), logging to an MLflow tracking
server whose backend store is PostgreSQL, against the local smoke run of the integration tests (Milan's per-day
result files and the tables that one dataset makes); and 8 processes logging to that server at once. The server
runs MLflow's basic-auth app: every job logs as the group's writer, whose credentials only the environment holds;
an unauthenticated request gets 401, a job or a workflow with a wrong password fails with the refusal named and
creates no run, and no secret of the engines shows in a log, a ``ps`` listing taken during the run, a param or a tag.

Collected with ``pytest --cluster`` only; the engines must be installed first (``tests/cluster/install.sh``, as root),
and a missing one fails the tests by name. The engines and the SLURM run start with the session (conftest.slurm_smoke,
cluster/background.py), then the local smoke run (conftest.local_smoke), so that their jobs use the core the unit tests
leave idle; pytest runs these tests once the local run's `tables` call has ended, while its `figures` call goes. The
measurements of the SLURM run (jobs, wall time, core-hours, against the local run) are printed in the summary and
written to ``results/cluster_run.json`` of its tree.
"""
from __future__ import annotations

import json
import multiprocessing
import os
import re
import subprocess
import time
from pathlib import Path

import polars as pl
import pytest
from mlflow.tracking import MlflowClient

from cluster.background import DATASETS, METHODS
from conftest import ROOT
from dswm.config import load_yaml
from smoke import TIMING

pytestmark = pytest.mark.cluster

SUBMITTED = re.compile(r"Job (\d+) has been submitted with SLURM jobid (\d+)")
TRACKED = ("train", "evaluate")
"""The smoke DAG's rules whose jobs are MLflow runs (the `tables calibrate` targets)."""
CONFIGURED = tuple(load_yaml(ROOT / "config.yaml")["methods"]["run"])
"""Every configured method: the local smoke run evaluates each of them on Milan (methods.only_on keeps some there),
the SLURM run those of METHODS."""
TIMED = re.compile(r"_ms(_|$)")
"""The per-day columns that measure time (plan_ms_per_slot, a solver's stat_solve_ms_median): they differ between
any two runs of a job, every other column is the same number."""


@pytest.fixture(scope="module")
def engines(slurm_smoke):
    """The loopback engines that the session started with the SLURM run (conftest.slurm_smoke)."""
    if slurm_smoke.error is not None:
        pytest.fail(f"the cluster engines or the SLURM run did not start:\n{slurm_smoke.error}")
    return slurm_smoke.engines


@pytest.fixture
def writer(engines, monkeypatch):
    """The writer's credentials in this process's environment (MLflow's client reads them there), for one test."""
    for var, value in engines.credentials.items():
        monkeypatch.setenv(var, value)
    return engines.credentials


def job_stats(text: str) -> dict[str, int]:
    """{rule: job count} of the "Job stats" table Snakemake prints first."""
    table = text.split("Job stats", 1)[1].split("total", 1)[0]
    return {rule: int(n) for rule, n in re.findall(r"^(\w+)\s+(\d+)$", table, flags=re.M)}


def sacct(ids) -> list[dict]:
    """sacct's record of the SLURM jobs ``ids`` (allocations only, not steps)."""
    fields = ["JobID", "JobName", "State", "ExitCode", "ElapsedRaw", "AllocCPUS", "CPUTimeRAW"]
    out = subprocess.run(["sacct", "-X", "-P", "-n", "-o", ",".join(fields), "-j", ",".join(map(str, ids))],
                         capture_output=True, text=True, check=True).stdout
    return [dict(zip(fields, line.split("|"))) for line in out.splitlines() if line.strip()]


def core_hours(work: Path, only: Path | None = None) -> float:
    """Core-hours of a smoke run's `tables calibrate` jobs in ``work``: the wall seconds of every job that has a
    benchmark file (each runs on one core), less those of the `figures` target; with ``only``, of the jobs that have a
    benchmark file in that tree too."""
    seconds = 0.0
    for tsv in (work / "results" / "benchmarks").rglob("*.tsv"):
        rel = tsv.relative_to(work / "results" / "benchmarks")
        if rel.parts[0] in ("extra_train", "extra_evaluate", "probe", "wm", "figures"):
            continue
        if only is not None and not (only / "results" / "benchmarks" / rel).exists():
            continue
        rows = tsv.read_text().splitlines()
        seconds += float(rows[-1].split("\t")[0])
    return seconds / 3600


@pytest.fixture(scope="module")
def slurm_run(engines, slurm_smoke, smoke_tables, request):
    """The Milan smoke DAG's `tables calibrate` in a fresh copy of the tree, every job but the local rules sent to
    SLURM, every run logged to the tracking server; started with the session (cluster/background.py), awaited here."""
    rc, text, wall = slurm_smoke.wait()
    assert rc == 0, f"{' '.join(slurm_smoke.argv)} exited with {rc}:\n{text[-8000:]}"
    work = slurm_smoke.work
    submitted = dict(SUBMITTED.findall(text))
    records = sacct(submitted.values())
    local = json.loads((smoke_tables / TIMING).read_text())
    summary = {
        "slurm": {"datasets": list(DATASETS), "jobs": len(submitted),
                  "local_rules_jobs": sum(job_stats(text).values()) - len(submitted), "wall_s": round(wall, 1),
                  "core_hours": round(sum(int(r["CPUTimeRAW"]) for r in records) / 3600, 3),
                  "beside": "the local smoke run and the unit tests (pytest --cluster) or the local smoke run alone "
                            "(pytest --cluster -m cluster), on 2 cores"},
        "local": {"datasets": ["milan", "shanghai", "yjmob"],
                  "jobs": sum(job_stats((smoke_tables / "smoke_tables.out").read_text()).values()),
                  "wall_s": local["tables"], "core_hours": round(core_hours(smoke_tables), 3),
                  "core_hours_of_the_slurm_runs_jobs": round(core_hours(smoke_tables, only=work), 3),
                  "beside": "the SLURM run and the unit tests, from the session's start"},
    }
    (work / "results" / "cluster_run.json").write_text(json.dumps(summary, indent=2))
    reporter = request.config.pluginmanager.get_plugin("terminalreporter")
    if reporter is not None:
        reporter.write_line(f"smoke DAG (tables calibrate) on SLURM: {summary}")
    return {"work": work, "text": text, "submitted": submitted, "sacct": records, "summary": summary,
            "ps": slurm_smoke.ps, "log": slurm_smoke.log}


def test_every_slurm_job_of_the_smoke_dag_completed(slurm_run):
    text, records = slurm_run["text"], slurm_run["sacct"]
    stats = job_stats(text)
    local = {"tables", "build_tables"}  # the Snakefile's localrules among the targets' jobs
    assert len(slurm_run["submitted"]) == sum(n for rule, n in stats.items() if rule not in local) == 15
    # every method of the SLURM run went through SLURM, in config.yaml's order, and every trained one's training
    # (dswm_plus evaluates dswm's)
    assert list(METHODS) == [m for m in CONFIGURED if m in METHODS] and len(METHODS) == 7
    assert stats["evaluate"] == len(METHODS) and stats["train"] == 2
    assert {r: stats[r] for r in ("demo_raw", "prepare", "calibrate", "eda", "mlflow_init", "audit_report")} == \
        dict.fromkeys(("demo_raw", "prepare", "calibrate", "eda", "mlflow_init", "audit_report"), 1)
    assert sorted(r["JobID"] for r in records) == sorted(slurm_run["submitted"].values())
    assert {(r["State"], r["ExitCode"]) for r in records} == {("COMPLETED", "0:0")}
    assert {r["AllocCPUS"] for r in records} == {"1"}  # each job asked for its rule's one thread
    assert len({r["JobName"] for r in records}) == 1  # one workflow's run id names them all


def test_every_per_day_result_equals_the_local_smoke_runs_but_its_timings(slurm_run, smoke_tables):
    from dswm.protocol.evaluation import read_method_record

    def days(work):
        return sorted(str(p.relative_to(work)) for p in (work / "results").glob("*/*/seed*/days.parquet"))

    local = days(smoke_tables)
    assert days(slurm_run["work"]) == [p for p in local
                                       if p.startswith("results/milan/") and p.split("/")[2] in METHODS]
    assert len(local) > len(days(slurm_run["work"])) == len(METHODS)
    for rel in days(slurm_run["work"]):
        ours, theirs = pl.read_parquet(slurm_run["work"] / rel), pl.read_parquet(smoke_tables / rel)
        timed = [c for c in ours.columns if TIMED.search(c)]
        assert ours.columns == theirs.columns and "plan_ms_per_slot" in timed, rel
        assert ours.drop(timed).equals(theirs.drop(timed)), rel
        assert read_method_record(slurm_run["work"] / rel) == read_method_record(smoke_tables / rel), rel
    solver = pl.read_parquet(slurm_run["work"] / "results" / "milan" / "jtoratc" / "seed0" / "days.parquet")
    assert [c for c in solver.columns if TIMED.search(c)] == ["plan_ms_per_slot", "stat_solve_ms_median"]


def test_the_tables_equal_the_local_smoke_runs_rows_of_its_methods_on_milan_byte_for_byte(slurm_run, smoke_tables):
    names = sorted(p.name for p in (smoke_tables / "results" / "tables").glob("*.csv"))
    assert names == ["cross_dataset.csv", "milan_main.csv", "room.csv"]
    assert sorted(p.name for p in (slurm_run["work"] / "results" / "tables").glob("*.csv")) == names
    ours = {name: (slurm_run["work"] / "results" / "tables" / name).read_bytes() for name in names}
    theirs = {name: (smoke_tables / "results" / "tables" / name).read_bytes() for name in names}
    # Table III, Table IV's rows and the room footnote's (its ladder's rungs keep their numbers): the local run's
    # header and its rows of Milan and of the SLURM run's methods, in the local run's order
    for name in names:
        header, *rows = theirs[name].splitlines(keepends=True)
        columns = header.rstrip(b"\r\n").split(b",")
        method, where = columns.index(b"method"), columns.index(b"dataset") if b"dataset" in columns else None
        kept = [row for row in rows if (where is None or row.split(b",")[where] == b"milan")
                and row.split(b",")[method].decode() in METHODS]
        assert len(rows) > len(kept) > 0, name
        assert ours[name] == b"".join([header, *kept]), name


def test_the_tracking_server_holds_one_finished_run_per_job(slurm_run, engines, writer):
    from prep.rawio import sha256_file

    client = MlflowClient(tracking_uri=engines.mlflow_uri)
    exp = client.get_experiment_by_name("dswm")
    assert exp is not None, f"no experiment 'dswm' on {engines.mlflow_uri}: the jobs did not log to the server"
    assert exp.tags["mlflow.experimentKind"] == "custom_model_development"
    assert exp.artifact_location == (slurm_run["work"] / "results" / "mlartifacts").resolve().as_uri()
    # mlflow_init created the experiment of the figures' runs on the server too, beside it
    figures = client.get_experiment_by_name("dswm-figures")
    assert figures is not None and figures.artifact_location == exp.artifact_location
    assert figures.tags["mlflow.experimentKind"] == "custom_model_development"
    workdir = str(slurm_run["work"].resolve())
    runs = client.search_runs([exp.experiment_id], filter_string=f"tags.workdir = '{workdir}'", max_results=1000)
    keys = sorted(r.data.tags["job_key"] for r in runs)
    stats = job_stats(slurm_run["text"])
    assert len(keys) == sum(stats[rule] for rule in TRACKED) == 9
    assert len(set(keys)) == len(keys)  # one run per job
    assert {r.info.status for r in runs} == {"FINISHED"}
    evaluations = [r for r in runs if r.data.tags["stage"] == "evaluate"]
    assert sorted(r.data.tags["method"] for r in evaluations) == sorted(METHODS)
    tensor = sha256_file(slurm_run["work"] / "results" / "data" / "milan" / "demand.parquet")[:16]
    for r in evaluations:  # each carries its demand tensor and its result file
        (entry,) = r.inputs.dataset_inputs
        assert (entry.dataset.name, entry.dataset.digest) == (r.data.tags["dataset"], tensor) == ("milan", tensor)
    one = next(r for r in evaluations if r.data.tags["job_key"] == "evaluate/milan/greedy/seed0")
    assert "days.parquet" in [a.path for a in client.list_artifacts(one.info.run_id)]
    assert {"id/sr_mean", "ood/sr_mean"} <= set(one.data.metrics)


HTTP = load_yaml(ROOT / "config.yaml")["mlflow"]["http"]
"""The retries, backoff and timeout of config.yaml's ``mlflow.http``: the writers' requests wait like a job's."""


def _writer(uri: str, experiment_id: str, index: int, barrier, out) -> None:
    """One of the concurrent writers: a run with params, 20 batches of metrics, tags and an end, its HTTP settings
    those of a job (:data:`HTTP`), not whatever the test process's environment held."""
    try:
        from mlflow.entities import Metric, Param, RunTag

        from dswm.pipeline.tracking import client_for

        client = client_for({"tracking_uri": uri, "http": HTTP})
        barrier.wait(timeout=60)
        run = client.create_run(experiment_id, tags={"writer": str(index)})
        client.log_batch(run.info.run_id, params=[Param(f"p{k}", str(k * index)) for k in range(50)])
        for step in range(20):
            now = int(time.time() * 1000)
            client.log_batch(run.info.run_id, metrics=[Metric(f"m{k}", float(index + step + k), now, step)
                                                       for k in range(25)],
                             tags=[RunTag("step", str(step))])
        client.set_terminated(run.info.run_id, "FINISHED")
        out.put((index, run.info.run_id, None))
    except Exception as err:  # reported to the test, which fails naming it
        out.put((index, None, f"{type(err).__name__}: {err}"))


def test_eight_concurrent_writers_to_the_postgresql_backed_server_all_complete(engines, writer):
    client = MlflowClient(tracking_uri=engines.mlflow_uri)
    exp_id = client.create_experiment("concurrent-writers")
    ctx = multiprocessing.get_context("spawn")
    barrier, out = ctx.Barrier(8), ctx.Queue()
    procs = [ctx.Process(target=_writer, args=(engines.mlflow_uri, exp_id, i, barrier, out)) for i in range(8)]
    for p in procs:
        p.start()
    results = [out.get(timeout=300) for _ in procs]
    for p in procs:
        p.join(timeout=60)
    errors = [(i, e) for i, _, e in results if e is not None]
    assert errors == [] and [p.exitcode for p in procs] == [0] * 8
    runs = client.search_runs([exp_id], max_results=100)
    assert len(runs) == 8 and {r.info.status for r in runs} == {"FINISHED"}
    for r in runs:
        index = int(r.data.tags["writer"])
        assert len(r.data.params) == 50 and r.data.params["p3"] == str(3 * index)
        assert len(r.data.metrics) == 25 and r.data.tags["step"] == "19"
        history = client.get_metric_history(r.info.run_id, "m0")
        assert [m.value for m in sorted(history, key=lambda m: m.step)] == [float(index + s) for s in range(20)]


# ---------------------------------------------------------------------------- the authenticated server

SEARCH = "/api/2.0/mlflow/experiments/search?max_results=1"


def test_an_unauthenticated_rest_request_gets_401_and_the_writer_gets_in(engines):
    status, text = engines.rest("GET", SEARCH)
    assert (status, text.startswith("You are not authenticated")) == (401, True)
    assert engines.rest("GET", SEARCH, user=(engines.writer, "a-wrong-password-123"))[0] == 401
    assert engines.rest("GET", SEARCH, user=(engines.writer, engines.passwords["writer"]))[0] == 200
    assert engines.rest("GET", "/health")[0] == 200  # the one open route: a load balancer's probe


def _runs_of_the_tree(engines, work):
    """{run id: job key} of every run (any status, deleted ones too) the SLURM tree logged, read as the admin."""
    import base64
    import json
    import urllib.request

    found = {}
    for name in ("dswm", "dswm-figures"):
        status, text = engines.rest("GET", f"/api/2.0/mlflow/experiments/get-by-name?experiment_name={name}",
                                    user=("admin", engines.passwords["admin"]))
        assert status == 200, text
        exp_id = json.loads(text)["experiment"]["experiment_id"]
        req = urllib.request.Request(engines.mlflow_uri + "/api/2.0/mlflow/runs/search", method="POST",
                                     data=json.dumps({"experiment_ids": [exp_id], "max_results": 1000,
                                                      "run_view_type": "ALL"}).encode(),
                                     headers={"Content-Type": "application/json", "Authorization": "Basic " +
                                              base64.b64encode(f"admin:{engines.passwords['admin']}".encode())
                                              .decode()})
        with urllib.request.urlopen(req, timeout=30) as answer:
            for run in json.loads(answer.read()).get("runs", []):
                tags = {t["key"]: t["value"] for t in run["data"].get("tags", [])}
                if tags.get("workdir") == str(work.resolve()):
                    found[run["info"]["run_id"]] = tags.get("job_key")
    return found


def refusals(engines) -> int:
    """How many requests the tracking server has answered 401 so far (its log has a line per request)."""
    return (engines.root / "log" / "mlflow.out").read_text(errors="replace").count('" 401 ')


def refusal(uri: str, call: str = "get_experiment_by_name") -> str:
    """The error of a call the server at ``uri`` refused with 401, the credentials taken from the environment."""
    return (f"MLflow at {uri}: {call} failed: the server refused the credentials (HTTP 401, not authenticated: user "
            f"or password wrong or missing; they came from MLFLOW_TRACKING_USERNAME and MLFLOW_TRACKING_PASSWORD in "
            f"the environment); not retried")


WRONG = "not-the-writers-password-987"


def test_a_slurm_job_with_a_wrong_password_fails_naming_the_refusal_and_creates_no_run(slurm_run, engines):
    """One SLURM job opens the run of an evaluate job (dswm.pipeline.tracking.job_run) with the writer's name and a
    wrong password in its environment: it fails at its first request with the message of a refusal, and the server
    holds no run of it."""
    import json
    import sys

    work = slurm_run["work"]
    before = _runs_of_the_tree(engines, work)
    mlflow_cfg = {"tracking_uri": engines.mlflow_uri, "store": "results/mlflow.db",
                  "artifacts": "results/mlartifacts", "experiment": "dswm", "batch_size": 1000,
                  "http": {"max_retries": 5, "backoff_factor": 2, "timeout_s": 60}, "unlogged": "results/unlogged"}
    script = work / "wrong_password_job.py"
    script.write_text(
        "import json, sys\n"
        "from dswm.pipeline.tracking import job_run\n"
        f"cfg = json.loads({json.dumps(json.dumps(mlflow_cfg))})\n"
        "with job_run(mlflow_cfg=cfg, settings={'profile': 'smoke'}, stage='evaluate', dataset='milan',\n"
        "             method='greedy', seed=77, config_hash='x', keep=['results/milan/greedy/seed0/days.parquet']):\n"
        "    sys.exit('the body must not run')\n")
    log = work / "logs" / "slurm" / "wrong_password_job.log"
    env = {**os.environ, "MLFLOW_TRACKING_USERNAME": engines.writer, "MLFLOW_TRACKING_PASSWORD": WRONG,
           "PYTHONPATH": f"{work / 'src'}{os.pathsep}{work}"}
    refused = refusals(engines)
    done = subprocess.run(["sbatch", "--wait", "--export=ALL", "--cpus-per-task=1", "--mem=1000",
                           f"--output={log}", f"--wrap={sys.executable} {script.name}"],
                          cwd=work, env=env, capture_output=True, text=True, timeout=600)
    text = log.read_text(errors="replace")
    assert done.returncode != 0, text
    assert refusal(engines.mlflow_uri) in text and "nothing was computed" in text
    assert "the body must not run" not in text and WRONG not in text + done.stdout + done.stderr
    assert not (work / "results" / "unlogged" / "evaluate" / "milan" / "greedy" / "seed77").exists()
    assert refusals(engines) == refused + 1  # one request, refused, not retried (mlflow.http allows 5)
    assert _runs_of_the_tree(engines, work) == before and "evaluate/milan/greedy/seed77" not in before.values()


def test_a_workflow_with_a_wrong_password_stops_before_any_job_and_creates_no_run(slurm_run, engines, tmp_path):
    """The SLURM tree's evaluation of greedy, forced to run again with a wrong password: the workflow stops as it
    starts (its first request to the server), submits nothing, and its result file and the server's runs stay."""
    from cluster.background import OVERLAY
    from smoke import command

    work = slurm_run["work"]
    days = work / "results" / "milan" / "greedy" / "seed0" / "days.parquet"
    before, data, refused = _runs_of_the_tree(engines, work), days.read_bytes(), refusals(engines)
    argv, env = command(str(days.relative_to(work)), "--configfile", OVERLAY, "--executor", "slurm",
                        "--profile", "profiles/slurm", "--jobs", "1", "--forcerun", "evaluate",
                        config=[f"mlflow={{tracking_uri: '{engines.mlflow_uri}'}}"],
                        env={"MLFLOW_TRACKING_USERNAME": engines.writer, "MLFLOW_TRACKING_PASSWORD": WRONG})
    done = subprocess.run(argv, cwd=work, env=env, capture_output=True, text=True, timeout=600)
    out = done.stdout + done.stderr
    assert done.returncode != 0, out[-4000:]
    assert refusal(engines.mlflow_uri) in out and WRONG not in out
    assert not SUBMITTED.search(out) and refusals(engines) == refused + 1
    assert days.read_bytes() == data and _runs_of_the_tree(engines, work) == before


def test_no_secret_shows_in_a_log_a_ps_listing_a_param_or_a_tag(slurm_run, engines, writer):
    secrets = engines.secrets()
    work, watch = slurm_run["work"], slurm_run["ps"]
    # every `ps` listing taken while the SLURM run went: the jobs' command lines were among them, no secret was
    assert watch.listings > 30 and watch.job_lines > 0
    assert watch.leaks == []
    # every log of the run: the rules' logs, SLURM's log of every job (all kept), Snakemake's own, and its output
    logs = [p for d in ("logs", ".snakemake/log") for p in (work / d).rglob("*") if p.is_file()]
    assert len(list((work / "logs" / "slurm").glob("rule_*/**/*.log"))) == 15  # SLURM's log of every job, kept
    logs += [slurm_run["log"], *(engines.root / "log").rglob("*")]
    leaked = [str(p) for p in logs if p.is_file() and any(s.encode() in p.read_bytes() for s in secrets)]
    assert leaked == []
    # every param and tag of every run the tree logged
    client = MlflowClient(tracking_uri=engines.mlflow_uri)
    exps = [client.get_experiment_by_name(n) for n in ("dswm", "dswm-figures")]
    runs = client.search_runs([e.experiment_id for e in exps if e is not None], max_results=1000,
                              filter_string=f"tags.workdir = '{work.resolve()}'")
    assert len(runs) == 9
    texts = [f"{k}={v}" for r in runs for k, v in (*r.data.params.items(), *r.data.tags.items())]
    assert len(texts) > 9 * 10 and [t for t in texts if any(s in t for s in secrets)] == []
