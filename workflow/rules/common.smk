# Helpers shared by every rule file: config resolution, validation and wildcard constraints.
import sys
from pathlib import Path

sys.path.insert(0, str(Path(workflow.basedir) / "src"))

wildcard_constraints:
    dataset="milan|shanghai|yjmob",
    seed=r"\d+",
