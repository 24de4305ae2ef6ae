"""The real engines of a cluster run, started on this machine's loopback for the `cluster` tests.

:class:`LoopbackEngines` starts, each as a child process whose PID it keeps:

* ``munged`` with its own key and socket (SLURM's authentication);
* MariaDB and ``slurmdbd``: SLURM's accounting, without which ``sacct`` (the executor plugin's status query and
  the test's record of every job) answers "accounting storage is disabled";
* ``slurmctld`` and one ``slurmd`` on 127.0.0.1: cons_tres, no cgroup (proctrack/linuxproc, task/none), the
  machine's CPUs;
* PostgreSQL, its ``postgres`` user with a password (scram-sha-256) that only a ``.pgpass`` file holds
  (``PGPASSFILE``), and ``mlflow server --app-name basic-auth`` with it as the backend store (a URI without the
  password), the artifact root a local directory (the "shared filesystem" of a one-node cluster). The server's admin
  is created from ``MLFLOW_AUTH_ADMIN_PASSWORD`` in its environment, and the admin creates the group's writer
  (:attr:`LoopbackEngines.credentials`) through the server's REST API, as docs/CLUSTER.md does. Every password is
  random, made at start, and on no command line (:meth:`LoopbackEngines.secrets` lists them for the tests).

Every port is a free loopback port picked at start. :meth:`LoopbackEngines.stop` stops what was started, by PID,
in reverse order. Nothing is installed here (``tests/cluster/install.sh`` does that); :func:`missing` names what
is absent. SLURM's job steps (``srun`` inside a job, which the executor plugin runs with a cleaned environment)
read ``/etc/slurm/slurm.conf``; the file is written there, marked as this harness's, and removed at stop, and an
existing file that is not this harness's is never overwritten.

Run by hand: ``python tests/cluster/engines.py`` starts everything, prints the addresses and waits for Ctrl-C.
"""
from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from dataclasses import dataclass, field
from pathlib import Path

if __name__ == "__main__":  # run by hand: tests/ holds the shared helpers that pytest puts on the path
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from smoke import stop  # noqa: E402

SLURM_CONF = Path("/etc/slurm/slurm.conf")
SLURMDBD_CONF = SLURM_CONF.with_name("slurmdbd.conf")
MARK = "# written by tests/cluster/engines.py (the loopback cluster of the `cluster` tests); removed at its stop"
CLUSTER = "dswmloop"
NODE = "localhost"
PG_BIN = sorted(Path("/usr/lib/postgresql").glob("*/bin"))
COMMANDS = ("munged", "mariadbd", "mariadb-install-db", "slurmdbd", "slurmctld", "slurmd", "sbatch", "sacct",
            "sacctmgr", "srun")


def missing() -> list[str]:
    """The engines' programs (and the Python packages the run needs) that this machine lacks; empty when all are
    present."""
    absent = [c for c in COMMANDS if shutil.which(c) is None and not Path("/usr/sbin", c).exists()]
    if not PG_BIN or not (PG_BIN[-1] / "postgres").exists():
        absent.append("postgresql (/usr/lib/postgresql/*/bin/postgres)")
    for module, package in (("psycopg2", "psycopg2-binary"),
                            ("snakemake_executor_plugin_slurm", "snakemake-executor-plugin-slurm"),
                            ("flask_wtf", "Flask-WTF (mlflow[auth]: the basic-auth app of the tracking server)")):
        try:
            __import__(module)
        except ImportError:
            absent.append(f"python package {package}")
    if os.geteuid() != 0:
        absent.append("root (slurmd and the SLURM configuration in /etc/slurm need it)")
    return absent


def _memory_mb() -> int:
    """90% of this machine's memory in MB: the node's RealMemory (slurmd drains a node that claims more than it has;
    what the rules ask for, `resources` in config.yaml, then limits how many jobs run at once as on a real node)."""
    for line in Path("/proc/meminfo").read_text().splitlines():
        if line.startswith("MemTotal:"):
            return int(int(line.split()[1]) / 1024 * 0.9)
    raise RuntimeError("/proc/meminfo has no MemTotal line")


def free_port() -> int:
    """A TCP port on 127.0.0.1 that nothing listens on now."""
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _which(name: str) -> str:
    found = shutil.which(name) or (str(Path("/usr/sbin", name)) if Path("/usr/sbin", name).exists() else None)
    if found is None:
        raise FileNotFoundError(f"{name}: not installed (run tests/cluster/install.sh as root)")
    return found


def _wait(check, what: str, log: Path | None, timeout: float = 60.0, proc: subprocess.Popen | None = None) -> None:
    """Poll ``check()`` until it is true; raise naming ``what`` and the end of ``log`` when it never is."""
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        with contextlib.suppress(Exception):
            if check():
                return
        if proc is not None and proc.poll() is not None:
            break
        time.sleep(0.2)
    tail = log.read_text(errors="replace")[-3000:] if log is not None and log.exists() else "(no log)"
    state = f"exited with {proc.returncode}" if proc is not None and proc.poll() is not None else "still not ready"
    raise RuntimeError(f"{what} did not start ({state} after {timeout:.0f} s); end of {log}:\n{tail}")


def _listening(port: int) -> bool:
    with socket.socket() as s:
        s.settimeout(0.5)
        return s.connect_ex(("127.0.0.1", port)) == 0


@dataclass
class LoopbackEngines:
    """SLURM (with accounting), PostgreSQL and an MLflow tracking server on 127.0.0.1, under ``root``."""

    root: Path
    cpus: int = field(default_factory=lambda: os.cpu_count() or 1)
    memory_mb: int = field(default_factory=lambda: _memory_mb())
    procs: list[tuple[str, subprocess.Popen]] = field(default_factory=list)
    ports: dict[str, int] = field(default_factory=dict)
    wrote_conf: bool = False
    pg_root: Path | None = None
    passwords: dict[str, str] = field(default_factory=lambda: {
        "postgres": secrets.token_urlsafe(18), "admin": secrets.token_urlsafe(18),
        "writer": secrets.token_urlsafe(18), "flask_secret_key": secrets.token_urlsafe(24)})
    """Made at start, each random; none is ever on a command line."""
    writer: str = "dswm-writer"
    """The group's writer on the tracking server: the user every job logs as."""

    # ---- addresses -------------------------------------------------------------------------------------------
    @property
    def mlflow_uri(self) -> str:
        return f"http://127.0.0.1:{self.ports['mlflow']}"

    @property
    def postgres_uri(self) -> str:
        return f"postgresql://postgres@127.0.0.1:{self.ports['postgres']}/mlflow"

    @property
    def artifacts(self) -> Path:
        return self.root / "mlartifacts"

    @property
    def pgpass(self) -> Path:
        """The ``.pgpass`` file (mode 0600) from which libpq takes the database password (``PGPASSFILE``)."""
        return self.root / "pgpass"

    @property
    def credentials(self) -> dict[str, str]:
        """The writer's credentials as a job's environment holds them (MLflow's client reads them there)."""
        return {"MLFLOW_TRACKING_USERNAME": self.writer, "MLFLOW_TRACKING_PASSWORD": self.passwords["writer"]}

    def secrets(self) -> list[str]:
        """Every password and key of the engines: none may appear in a command line, a log, a param or a tag."""
        return list(self.passwords.values())

    def pids(self) -> dict[str, int]:
        return {name: p.pid for name, p in self.procs}

    # ---- start and stop ----------------------------------------------------------------------------------------
    def start(self) -> "LoopbackEngines":
        """Start every engine; on any failure stop what was started and raise naming the engine and its log."""
        absent = missing()
        if absent:
            raise RuntimeError("the cluster engines cannot start; missing: " + "; ".join(absent) +
                               " (run tests/cluster/install.sh as root)")
        self.root.mkdir(parents=True, exist_ok=True)
        (self.root / "log").mkdir(exist_ok=True)
        self.ports = {k: free_port() for k in ("mariadb", "slurmdbd", "slurmctld", "slurmd", "postgres", "mlflow")}
        try:
            self._munge()
            self._mariadb()
            self._slurm()
            self._postgres()
            self._mlflow()
        except BaseException:
            self.stop()
            raise
        return self

    def stop(self) -> None:
        """Stop every engine started, by PID, newest first (SIGTERM, then SIGKILL after 20 s); remove the SLURM
        configuration this harness wrote."""
        for name, proc in reversed(self.procs):
            stop(proc, grace=20)
        self.procs.clear()
        if self.pg_root is not None:
            shutil.rmtree(self.pg_root, ignore_errors=True)
            self.pg_root = None
        if self.wrote_conf:
            for conf in (SLURM_CONF, SLURMDBD_CONF):
                if conf.exists() and conf.read_text().startswith(MARK):
                    conf.unlink()
            self.wrote_conf = False

    def __enter__(self) -> "LoopbackEngines":
        return self.start()

    def __exit__(self, *exc) -> None:
        self.stop()

    def _spawn(self, name: str, argv: list[str], **kwargs) -> subprocess.Popen:
        """Start ``argv`` in its own process group (so its workers stop with it), output to log/<name>.out."""
        out = open(self.root / "log" / f"{name}.out", "ab")
        proc = subprocess.Popen(argv, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
                                start_new_session=True, **kwargs)
        out.close()
        self.procs.append((name, proc))
        return proc

    def _run(self, argv: list[str], what: str, **kwargs) -> str:
        done = subprocess.run(argv, capture_output=True, text=True, **kwargs)
        if done.returncode != 0:
            raise RuntimeError(f"{what}: {' '.join(argv)} exited with {done.returncode}:\n{done.stdout}{done.stderr}")
        return done.stdout

    # ---- the engines -------------------------------------------------------------------------------------------
    def _munge(self) -> None:
        d = self.root / "munge"
        d.mkdir(mode=0o700, exist_ok=True)
        key = d / "munge.key"
        key.write_bytes(secrets.token_bytes(1024))
        key.chmod(0o400)
        self.munge_socket = d / "munge.socket"
        proc = self._spawn("munged", [_which("munged"), "--foreground", "--force", f"--key-file={key}",
                                      f"--socket={self.munge_socket}", f"--pid-file={d / 'munged.pid'}",
                                      f"--log-file={self.root / 'log' / 'munged.log'}",
                                      f"--seed-file={d / 'munged.seed'}"])
        _wait(self.munge_socket.exists, "munged", self.root / "log" / "munged.log", proc=proc)

    def _mariadb(self) -> None:
        data = self.root / "mariadb"
        self._run([_which("mariadb-install-db"), "--user=root", f"--datadir={data}", "--skip-test-db",
                   "--auth-root-authentication-method=normal"], "MariaDB's data directory")
        log = self.root / "log" / "mariadb.err"
        proc = self._spawn("mariadbd", [_which("mariadbd"), "--no-defaults", "--user=root", f"--datadir={data}",
                                        f"--socket={self.root / 'mariadb.sock'}", f"--port={self.ports['mariadb']}",
                                        "--bind-address=127.0.0.1", f"--log-error={log}", "--skip-log-bin",
                                        "--skip-grant-tables", "--innodb-buffer-pool-size=64M"])
        _wait(lambda: _listening(self.ports["mariadb"]), "MariaDB", log, proc=proc)

    def _slurm(self) -> None:
        for conf in (SLURM_CONF, SLURMDBD_CONF):
            if conf.exists() and not conf.read_text().startswith(MARK):
                raise RuntimeError(f"{conf} exists and is not this harness's: a SLURM installation is configured on "
                                   f"this machine; the loopback cluster will not overwrite it")
        state = self.root / "slurm"
        for sub in ("state", "spool"):
            (state / sub).mkdir(parents=True, exist_ok=True)
        log = self.root / "log"
        auth = f"AuthInfo=socket={self.munge_socket}"
        SLURM_CONF.parent.mkdir(parents=True, exist_ok=True)
        self.wrote_conf = True
        SLURMDBD_CONF.write_text("\n".join([
            MARK, "AuthType=auth/munge", auth, "DbdHost=localhost", "DbdAddr=127.0.0.1",
            f"DbdPort={self.ports['slurmdbd']}", "SlurmUser=root", f"LogFile={log / 'slurmdbd.log'}",
            f"PidFile={state / 'slurmdbd.pid'}", "StorageType=accounting_storage/mysql", "StorageHost=127.0.0.1",
            f"StoragePort={self.ports['mariadb']}", "StorageUser=root", "StorageLoc=slurm_acct_db", ""]))
        SLURMDBD_CONF.chmod(0o600)
        SLURM_CONF.write_text("\n".join([
            MARK, f"ClusterName={CLUSTER}", f"SlurmctldHost={NODE}(127.0.0.1)",
            f"SlurmctldPort={self.ports['slurmctld']}", f"SlurmdPort={self.ports['slurmd']}",
            "SlurmUser=root", "SlurmdUser=root", "AuthType=auth/munge", "CredType=cred/munge", auth,
            "MpiDefault=none", "ProctrackType=proctrack/linuxproc", "TaskPlugin=task/none",
            "SelectType=select/cons_tres", "SelectTypeParameters=CR_Core_Memory", "SchedulerType=sched/backfill",
            f"StateSaveLocation={state / 'state'}", f"SlurmdSpoolDir={state / 'spool'}",
            f"SlurmctldPidFile={state / 'slurmctld.pid'}", f"SlurmdPidFile={state / 'slurmd.pid'}",
            f"SlurmctldLogFile={log / 'slurmctld.log'}", f"SlurmdLogFile={log / 'slurmd.log'}",
            "ReturnToService=2", "MinJobAge=3600", "AccountingStorageType=accounting_storage/slurmdbd",
            "AccountingStorageHost=127.0.0.1", f"AccountingStoragePort={self.ports['slurmdbd']}",
            f"AccountingStoragePass={self.munge_socket}",  # the munge socket of the accounting connection
            "JobAcctGatherType=jobacct_gather/linux", "JobAcctGatherFrequency=30", "JobCompType=jobcomp/none",
            f"NodeName={NODE} NodeAddr=127.0.0.1 CPUs={self.cpus} RealMemory={self.memory_mb} State=UNKNOWN",
            f"PartitionName=loop Nodes={NODE} Default=YES MaxTime=INFINITE State=UP", ""]))
        proc = self._spawn("slurmdbd", [_which("slurmdbd"), "-D"])
        _wait(lambda: _listening(self.ports["slurmdbd"]), "slurmdbd", log / "slurmdbd.log", proc=proc)
        self._run([_which("sacctmgr"), "-i", "add", "cluster", CLUSTER], "registering the cluster with slurmdbd")
        proc = self._spawn("slurmctld", [_which("slurmctld"), "-D", "-i"])
        _wait(lambda: _listening(self.ports["slurmctld"]), "slurmctld", log / "slurmctld.log", proc=proc)
        proc = self._spawn("slurmd", [_which("slurmd"), "-D", "-N", NODE])
        _wait(lambda: "idle" in self._run(["sinfo", "-h", "-o", "%T"], "sinfo"), "slurmd (node idle)",
              log / "slurmd.log", proc=proc)

    def _postgres(self) -> None:
        bin_dir = PG_BIN[-1]
        # PostgreSQL runs as its own user, who cannot enter the caller's private directories (pytest's are 0700):
        # its data and logs go to a directory of its own, removed at stop.
        self.pg_root = Path(tempfile.mkdtemp(prefix="dswm-loopback-postgres-"))
        data = self.pg_root / "data"
        data.mkdir()
        (self.pg_root / "log").mkdir()
        for d in (self.pg_root, data, self.pg_root / "log"):
            shutil.chown(d, "postgres", "postgres")
        pwfile = self.pg_root / "pwfile"  # read once by initdb, then removed
        pwfile.write_text(self.passwords["postgres"] + "\n")
        pwfile.chmod(0o600)
        shutil.chown(pwfile, "postgres", "postgres")
        self._run([str(bin_dir / "initdb"), "-D", str(data), "-A", "scram-sha-256", "-U", "postgres",
                   f"--pwfile={pwfile}", "--no-sync"], "PostgreSQL's data directory", user="postgres", group="postgres")
        pwfile.unlink()
        self.pgpass.write_text(f"127.0.0.1:{self.ports['postgres']}:*:postgres:{self.passwords['postgres']}\n")
        self.pgpass.chmod(0o600)
        log = self.root / "log" / "postgres.log"
        proc = self._spawn("postgres", [str(bin_dir / "postgres"), "-D", str(data), "-p", str(self.ports["postgres"]),
                                        "-k", str(data), "-c", "listen_addresses=127.0.0.1", "-c", "fsync=off",
                                        "-c", f"log_directory={self.pg_root / 'log'}", "-c", "max_connections=100"],
                           user="postgres", group="postgres")
        _wait(lambda: _listening(self.ports["postgres"]), "PostgreSQL", self.root / "log" / "postgres.out",
              proc=proc)
        _wait(lambda: subprocess.run([str(bin_dir / "createdb"), "-h", "127.0.0.1", "-p", str(self.ports["postgres"]),
                                      "-U", "postgres", "-w", "mlflow"], capture_output=True,
                                     env={**os.environ, "PGPASSFILE": str(self.pgpass)}).returncode == 0,
              "the mlflow database", log, timeout=30)

    def _mlflow(self) -> None:
        """The tracking server with MLflow's basic-auth app, as docs/CLUSTER.md starts it: the auth settings in a file
        (``MLFLOW_AUTH_CONFIG_PATH``), the admin's password and the CSRF key in the server's environment, the database
        password in ``.pgpass``; then the admin creates the writer."""
        self.artifacts.mkdir(parents=True, exist_ok=True)
        auth = self.root / "basic_auth.ini"
        auth.write_text("[mlflow]\ndefault_permission = READ\n"
                        f"database_uri = sqlite:///{self.root / 'basic_auth.db'}\nadmin_username = admin\n"
                        "authorization_function = mlflow.server.auth:authenticate_request_basic_auth\n")
        auth.chmod(0o600)
        env = {**os.environ, "MLFLOW_AUTH_CONFIG_PATH": str(auth), "PGPASSFILE": str(self.pgpass),
               "MLFLOW_AUTH_ADMIN_PASSWORD": self.passwords["admin"],
               "MLFLOW_FLASK_SERVER_SECRET_KEY": self.passwords["flask_secret_key"]}
        for var in ("MLFLOW_TRACKING_USERNAME", "MLFLOW_TRACKING_PASSWORD"):
            env.pop(var, None)
        mlflow = str(Path(sys.executable).with_name("mlflow"))
        log = self.root / "log" / "mlflow.out"
        host = f"127.0.0.1:{self.ports['mlflow']}"
        proc = self._spawn("mlflow", [mlflow, "server", "--app-name", "basic-auth",
                                      "--backend-store-uri", self.postgres_uri,
                                      "--default-artifact-root", self.artifacts.as_uri(), "--no-serve-artifacts",
                                      "--host", "127.0.0.1", "--port", str(self.ports["mlflow"]),
                                      "--allowed-hosts", host, "--workers", "2"], env=env)
        _wait(lambda: urllib.request.urlopen(f"{self.mlflow_uri}/health", timeout=2).status == 200,
              "mlflow server", log, timeout=180, proc=proc)
        status, text = self.rest("POST", "/api/2.0/mlflow/users/create", user=("admin", self.passwords["admin"]),
                                 body={"username": self.writer, "password": self.passwords["writer"]})
        if status != 200:
            raise RuntimeError(f"the tracking server's admin could not create the user {self.writer!r}: HTTP {status}: "
                               f"{text[:500]}; end of {log}:\n{log.read_text(errors='replace')[-3000:]}")

    def rest(self, method: str, path: str, *, user: tuple[str, str] | None = None, body: dict | None = None):
        """(HTTP status, answer text) of a request to the tracking server, with basic authentication as ``user``
        (name, password) where given; the credentials go in a header, never in a URL or an argv."""
        import base64
        import json
        import urllib.error

        req = urllib.request.Request(self.mlflow_uri + path, method=method,
                                     data=None if body is None else json.dumps(body).encode(),
                                     headers={"Content-Type": "application/json"})
        if user is not None:
            req.add_header("Authorization", "Basic " + base64.b64encode(":".join(user).encode()).decode())
        try:
            with urllib.request.urlopen(req, timeout=30) as answer:
                return answer.status, answer.read().decode()
        except urllib.error.HTTPError as err:
            return err.code, err.read().decode(errors="replace")


def main() -> None:
    root = Path(sys.argv[1]) if len(sys.argv) > 1 else Path(tempfile.mkdtemp(prefix="dswm-loopback-"))
    with LoopbackEngines(root=root) as engines:
        print(f"SLURM cluster {CLUSTER!r} (slurmctld :{engines.ports['slurmctld']}), MLflow {engines.mlflow_uri} "
              f"on {engines.postgres_uri}; logs in {root / 'log'}; Ctrl-C stops everything", flush=True)
        with contextlib.suppress(KeyboardInterrupt):
            signal.pause()


if __name__ == "__main__":
    main()
