"""The prep rules' DAG (dry run) and the EDA statistics on a hand-made tensor."""
from __future__ import annotations

import re
import subprocess
import sys
from pathlib import Path

import numpy as np

from prep.eda import run_eda
from prep.tensor import DemandTensor, GridSpec

ROOT = Path(__file__).resolve().parents[1]


def test_dry_run_wires_demo_raw_prepare_and_the_kappa_reference():
    targets = [f"results/data/{d}/meta.json" for d in ("milan", "shanghai", "yjmob")]
    out = subprocess.run([str(Path(sys.executable).parent / "snakemake"), "-n", "--forceall", "--nolock",
                          "--cores", "2", *targets], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stdout + out.stderr
    text = out.stdout + out.stderr
    counts = dict(re.findall(r"^(demo_raw|prepare)\s+(\d+)$", text, flags=re.M))
    assert counts == {"demo_raw": "3", "prepare": "3"}
    # Shanghai and YJMob need Milan's training mean for kappa: Milan's meta.json is their input.
    for ds in ("shanghai", "yjmob"):
        block = re.search(rf"rule prepare:\n\s+input: ([^\n]+)\n\s+output: results/data/{ds}/", text)
        assert block and f"results/raw/{ds}/demo" in block.group(1) and "results/data/milan/meta.json" in block.group(1)
    block = re.search(r"rule prepare:\n\s+input: ([^\n]+)\n\s+output: results/data/milan/", text)
    assert block and block.group(1).strip() == "results/raw/milan/demo"


def test_eda_statistics_on_a_hand_made_tensor(tmp_path):
    demand = np.zeros((2, 144, 2, 2), dtype=np.float32)
    demand[0, 24:30, 0, 0] = 2.0  # weekday 04:00-05:00: cell (0,0)
    demand[0, 84:90, 1, 1] = 1.0  # weekday 14:00-15:00: cell (1,1)
    demand[1, 84:90, 1, 1] = 3.0  # weekend 14:00-15:00: cell (1,1)
    meta = {"dataset": "milan", "source": "demo", "p99": 1.0, "kappa": 1.0, "week": None,
            "days": [{"index": 0, "label": "2013-11-04", "split": "train", "weekday": 0, "weekend": False},
                     {"index": 1, "label": "2013-12-21", "split": "test", "weekday": 5, "weekend": True}],
            "eval_days": {"id": [], "ood": [1]}}
    t = DemandTensor(demand=demand, meta=meta, grid=GridSpec(rows=2, cols=2, cell_m=235.0))
    s = run_eda(t, json_path=tmp_path / "eda.json", png_path=tmp_path / "eda.png", top_frac=0.05)
    assert s["zero_cell_rate"] == 1 - 18 / (2 * 144 * 4)
    assert s["top5_share"] == 24 / 36  # one top cell of four: (1,1) carries 6 + 18 of 36
    assert s["hotspot_overlap_04h_14h"] == 0.0  # (0,0) leads at 04:00, (1,1) at 14:00
    assert s["daily_cycle"]["weekday"][24] == 2.0 and s["daily_cycle"]["weekend"][84] == 3.0
    assert [r["total"] for r in s["daily_totals"]] == [18.0, 18.0]
    assert [r["eval"] for r in s["daily_totals"]] == [None, "ood"]
    # Hotspot migration: no 2013-11-03 in this tensor, so the first training day's slots 0..50.
    mig = s["hotspot_migration"]
    assert mig["window"] == {"day": "2013-11-04", "day_index": 0, "first_slot": 0, "slots": 51,
                             "basis": "first training day"}
    assert mig["top_k"] == 1 and mig["lag_slots"] == 18
    assert mig["top_k_share_overlap"] is None  # no two frames 18 slots apart both hold demand (only 04:00-05:00)
    assert abs(mig["energy_outside_first_component"]) < 1e-12  # one map throughout
    assert (tmp_path / "eda.png").read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["eda.json", "eda.png"]
