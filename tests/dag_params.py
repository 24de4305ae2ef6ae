"""The rerun trigger of every job of a DAG, as Snakemake itself compares it: `python dag_params.py ROOT TARGET...
[--configfile FILE] [--config KEY=VALUE ...]` prints {"<rule> <first output>": [the job's params as Snakemake
records them in .snakemake/metadata]} as JSON (every job of the targets, as with --forceall).

Snakemake reruns a finished job when these differ from the ones it recorded ("Params have changed"), so two configs
that give a job the same list rerun nothing of it. Read through Snakemake's own API (its persistence's
serialization: an Untracked value is left out there, as in a real run), in a process of its own.
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path


def tracked_params(root: Path, targets: list[str], configfiles: list[Path], config: dict) -> dict[str, list]:
    from snakemake.api import SnakemakeApi
    from snakemake.settings.types import ConfigSettings, DAGSettings, OutputSettings, ResourceSettings

    with SnakemakeApi(OutputSettings(quiet={"all"})) as api:
        workflow_api = api.workflow(resource_settings=ResourceSettings(cores=1), snakefile=root / "Snakefile",
                                    workdir=root, config_settings=ConfigSettings(config=config,
                                                                               configfiles=configfiles))
        dag_api = workflow_api.dag(dag_settings=DAGSettings(targets=set(targets), forceall=True))
        workflow = dag_api.workflow_api._workflow
        workflow._prepare_dag(forceall=True, ignore_incomplete=True, lock_warn_only=True, nolock=True)
        workflow._build_dag()
        return {f"{job.rule.name} {job.output[0] if job.output else '-'}": workflow.persistence._params(job)
                for job in workflow.dag.jobs}


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("root", type=Path)
    parser.add_argument("targets", nargs="+")
    parser.add_argument("--configfile", type=Path, action="append", default=[])
    parser.add_argument("--config", nargs="*", default=[])
    args = parser.parse_args()
    from snakemake.cli import parse_config

    params = tracked_params(args.root.resolve(), args.targets, args.configfile, parse_config(args.config))
    print(json.dumps(params, sort_keys=True, default=str), file=sys.stdout)


if __name__ == "__main__":
    main()
