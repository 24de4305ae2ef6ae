"""Shared fixtures: the repository's scenario and small grids."""
from __future__ import annotations

import dataclasses
import os
from pathlib import Path

import pytest
import torch

from dswm.sim.scenario import load_scenario

ROOT = Path(__file__).resolve().parents[1]
SHARED = ROOT.parent / "shared"
LEARNING_BASELINES = {"ppo": "model-free RL", "sac": "model-free RL", "maddpg": "MARL", "ga_matr": "MARL",
                      "tdmpc": "model-based", "emorl_tcto": "multi-obj. RL",
                      "hrl_tpra": "hier. RL"}
"""The paper's learning baselines with their Table III class; each trains alone (no other method shares its model)."""
HTTP_ENV_PREFIX = "MLFLOW_HTTP_REQUEST_"
"""The prefix of the environment variables through which MLflow's REST client reads its retries, backoff and timeout
(dswm.pipeline.tracking.HTTP_ENV)."""


def pytest_addoption(parser):
    parser.addoption("--cluster", action="store_true",
                     help="also run the tests marked `cluster`: the smoke DAG on a real SLURM and an MLflow server on "
                          "PostgreSQL, started on loopback (install them first: tests/cluster/install.sh, as root)")


def pytest_collection_modifyitems(config, items):
    """Tests marked `cluster` need engines that `tests/cluster/install.sh` installs as root: they are collected with
    ``--cluster`` only, and a plain run says how many it left out."""
    # The tests that read the local smoke run come after every other test: that run, and with ``--cluster`` the
    # SLURM run, start with the session (local_smoke, slurm_smoke) and go on beside the unit tests, one process,
    # instead of after them. Those that read its `tables` call alone (the quick benchmark, and the cluster tests,
    # which read the SLURM run too) come before those that read its `figures` call, and so run while it goes.
    def order(item):
        uses, cluster = getattr(item, "fixturenames", ()), item.get_closest_marker("cluster") is not None
        return "smoke_run" in uses, "smoke_tables" in uses or cluster, cluster

    items.sort(key=order)
    if config.getoption("--cluster"):
        return
    left = [item for item in items if item.get_closest_marker("cluster")]
    if left:
        items[:] = [item for item in items if not item.get_closest_marker("cluster")]
        config.hook.pytest_deselected(items=left)
        config.stash[_CLUSTER_LEFT] = len(left)


_CLUSTER_LEFT = pytest.StashKey[int]()


def pytest_terminal_summary(terminalreporter, exitstatus, config):
    left = config.stash.get(_CLUSTER_LEFT, 0)
    if left:
        terminalreporter.write_line(f"{left} cluster test(s) not run: they need SLURM, PostgreSQL and an MLflow server "
                                    f"(as root: bash tests/cluster/install.sh, then pytest --cluster)", yellow=True)


@pytest.fixture(autouse=True)
def subnormals_kept():
    """Every test starts and ends in the CPU's default mode, subnormal floats computed: a job run in this process
    turns on their flushing (dswm.pipeline.subnormals) for the thread, and hypothesis refuses to draw floats under
    it."""
    torch.set_flush_denormal(False)
    yield
    torch.set_flush_denormal(False)


@pytest.fixture(autouse=True)
def mlflow_http_env_restored():
    """Every test ends with MLflow's HTTP settings (``MLFLOW_HTTP_REQUEST_*``) as it found them: a job opened in this
    process sets them for the process from its ``mlflow.http`` (dswm.pipeline.tracking.configure_http), and a later
    test, or a process it starts, would otherwise inherit one test's 5-second timeout."""
    before = {k: v for k, v in os.environ.items() if k.startswith(HTTP_ENV_PREFIX)}
    yield
    for key in [k for k in os.environ if k.startswith(HTTP_ENV_PREFIX)]:
        del os.environ[key]
    os.environ.update(before)


@pytest.fixture(autouse=True)
def one_thread():
    """Tests use small tensors: one torch thread is fastest, and immune to a busy machine's oversubscription
    (code under test may set its own thread count; it is restored after each test)."""
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(1)


@pytest.fixture(scope="session", autouse=True)
def slurm_smoke(request, tmp_path_factory):
    """With ``--cluster``: the loopback engines and the smoke DAG on SLURM, started as the session starts so that
    its jobs run beside the unit tests and the local smoke run (cluster/background.py); the cluster tests read it.
    Otherwise None."""
    if not request.config.getoption("--cluster"):
        yield None
        return
    from cluster.background import SlurmSmokeRun

    run = SlurmSmokeRun(root=tmp_path_factory.mktemp("slurm")).launch()
    yield run
    run.stop()


@pytest.fixture(scope="session", autouse=True)
def local_smoke(request, slurm_smoke, tmp_path_factory):
    """The local smoke run (smoke.LocalSmokeRun), started as the session starts when a collected test reads it, after
    the SLURM run of ``--cluster`` has started: both go on beside the unit tests, which pytest runs first; the tests
    that read them wait for them. Otherwise None."""
    needs = set().union(*(getattr(item, "fixturenames", ()) for item in request.session.items))
    calls = ("tables", "figures") if "smoke_run" in needs else ("tables",) if "smoke_tables" in needs else ()
    if not calls:
        yield None
        return
    from smoke import LocalSmokeRun

    run = LocalSmokeRun(tmp_path_factory.mktemp("smoke") / "repo", calls).launch()
    yield run
    run.stop()


@pytest.fixture(scope="session")
def smoke_tables(local_smoke):
    """A copy of the working tree where the smoke DAG's `tables calibrate` has run (the cluster tests compare a SLURM
    run with it; smoke_run adds `figures`)."""
    return local_smoke.result("tables")


@pytest.fixture(scope="session")
def smoke_run(smoke_tables, local_smoke):
    """The tree of smoke_tables where the smoke DAG's `figures` and `room_fill` have run too (the integration tests
    check it)."""
    return local_smoke.result("figures")


@pytest.fixture(scope="session")
def scenario():
    """The scenario of config.yaml (u: the demo calibration, DEMO_INTENSITY, where config.yaml says calibrate)."""
    return load_scenario(ROOT / "config.yaml", standin=True)


@pytest.fixture
def make_scenario(scenario):
    """The config scenario with some constants replaced."""
    def make(**changes):
        return dataclasses.replace(scenario, **changes)
    return make


def dataset_of(config: dict, dataset: str):
    """The typed ``datasets.<dataset>`` section of a config mapping."""
    from prep.config import dataset_from_plain

    return dataset_from_plain(dataset, config["datasets"][dataset])


def prepare_from_config(config: dict, dataset: str, **kwargs):
    """``prep.pipeline.prepare_dataset`` with the typed sections of a config mapping."""
    from prep.config import common_from_plain
    from prep.pipeline import prepare_dataset

    return prepare_dataset(dataset_of(config, dataset), common_from_plain(config["datasets"]["common"]), dataset,
                           **kwargs)


def dry_run_blocks(text: str) -> dict[tuple[str, str], str]:
    """{(rule, first output): the job's block} of every job a ``snakemake -n`` output printed."""
    import re

    jobs = {}
    for block in re.split(r"\n(?=(?:local)?rule \w+:)", text):
        head = re.match(r"(?:local)?rule (\w+):", block)
        out = re.search(r"^\s+output: ([^,\n]+)", block, flags=re.M)
        if head and out:
            jobs[(head.group(1), out.group(1))] = block
    return jobs
