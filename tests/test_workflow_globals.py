"""The workflow's top-level names are Snakemake's job-formatting namespace: a remote executor formats its job
script's name (`snakejob.{name}.{jobid}.sh`) with them as keywords of snakemake.utils.format, so a global that
shares a name with one of format's own parameters breaks the submission of every job with a long input list."""
from __future__ import annotations

import ast
import inspect
from pathlib import Path

from snakemake.utils import format as snakemake_format

ROOT = Path(__file__).resolve().parents[1]


def workflow_globals() -> dict[str, str]:
    """{name: file} of every function and variable defined at the top level of the Snakefile and the rule files,
    read from their Python lines (the rule blocks are skipped: they are not Python)."""
    names = {}
    for path in [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]:
        lines = path.read_text().splitlines()
        for i, line in enumerate(lines):
            head = line.split("#", 1)[0]
            if head.startswith("def "):
                names[head[4:].split("(", 1)[0].strip()] = path.name
            elif head and not head[0].isspace() and "=" in head and not head.startswith(("rule ", "include", "@")):
                target = head.split("=", 1)[0]
                if target.strip().isidentifier():
                    names[target.strip()] = path.name
    return names


def test_no_workflow_global_shadows_a_parameter_of_snakemakes_format():
    names = workflow_globals()
    assert {"DATASETS", "job_resources", "_alternatives"} <= set(names)  # the reader finds both kinds
    reserved = set(inspect.signature(snakemake_format).parameters) - {"args", "kwargs"}
    assert reserved >= {"_pattern", "stepout"}
    clashes = {name: names[name] for name in reserved & set(names)}
    assert clashes == {}, f"rename these workflow globals (they break job submission on a cluster): {clashes}"


def test_helper_functions_live_in_common_smk():
    """The other rule files hold rules (and the names their rules read) only; every helper function is in
    workflow/rules/common.smk, where a reader looks for it."""
    defined = {}
    for path in [ROOT / "Snakefile", *sorted((ROOT / "workflow" / "rules").glob("*.smk"))]:
        for line in path.read_text().splitlines():
            if line.lstrip().startswith("def "):
                defined.setdefault(path.name, []).append(line.strip()[4:].split("(", 1)[0])
    assert {"probe_files", "main_days", "wm_model", "_alternatives"} <= set(defined["common.smk"])
    elsewhere = {name: funcs for name, funcs in defined.items() if name != "common.smk"}
    assert elsewhere == {}, f"move these helper functions into workflow/rules/common.smk: {elsewhere}"


def test_the_dataset_wildcard_takes_the_datasets_the_config_knows():
    """The `dataset` constraint is built from config.yaml's `datasets:` section, not written out: common.smk names
    no dataset, and the section's datasets are the three the constraint allowed when it was written by hand."""
    import yaml

    from prep.config import DATASETS

    common = (ROOT / "workflow" / "rules" / "common.smk").read_text()
    assert "dataset=_alternatives(KNOWN_DATASETS)," in common
    assert [name for name in DATASETS if name in common] == []
    config = yaml.safe_load((ROOT / "config.yaml").read_text())
    assert [name for name in config["datasets"] if name in DATASETS] == ["milan", "shanghai", "yjmob"]
