"""Selection on training days: the split of the training days and the choice rules (dswm.protocol.selection)."""
import types

import numpy as np
import pytest

from dswm.methods.search import SearchSettings
from dswm.protocol import selection


def tensor(n_train, n_test=3):
    days = list(range(n_train + n_test))
    return types.SimpleNamespace(train_days=np.array(days[:n_train]), labels=[f"d{d}" for d in days],
                                 meta={"dataset": "toy"})


def test_training_days_split_in_time_order_and_test_days_are_never_used():
    fit, val = selection.split_training_days(tensor(10), 7)
    assert fit == list(range(7)) and val == [7, 8, 9]       # the test days 10..12 are in neither
    with pytest.raises(ValueError, match="toy: 7 training day.*fit_days = 7.*at least 8"):
        selection.split_training_days(tensor(7), 7)


CANDIDATES = [SearchSettings(sweeps=s, lattice=7, refine=r, bw_logits=()) for s, r in ((1, 0), (2, 0), (3, 2))]


@pytest.mark.parametrize("scores, budget, chosen", [
    ({1: (0.70, 10.0), 2: (0.75, 20.0), 3: (0.76, 90.0)}, 100.0, 3),   # the best within the budget
    ({1: (0.70, 10.0), 2: (0.75, 20.0), 3: (0.76, 90.0)}, 50.0, 2),    # the best is over the budget
    ({1: (0.75, 10.0), 2: (0.75, 20.0), 3: (0.74, 30.0)}, 50.0, 1),    # a tie goes to the earlier candidate
    ({1: (0.70, 60.0), 2: (0.75, 70.0), 3: (0.76, 90.0)}, 50.0, None),  # none within the budget
])
def test_the_search_is_the_best_served_ratio_within_the_budget(monkeypatch, scores, budget, chosen):
    def fake_score(*, controller, **kw):
        sr, ms = scores[controller.sweeps]
        return {"sr_mean": sr, "sr_per_day": {}, "ms_per_slot": ms}

    monkeypatch.setattr(selection, "score_days", fake_score)
    out = selection.select_search(make=lambda c: c, candidates=CANDIDATES, budget_ms=budget)
    assert [r["sr_mean"] for r in out["candidates"]] == [scores[k][0] for k in (1, 2, 3)]
    want = None if chosen is None else {"sweeps": chosen, "lattice": 7, "refine": 2 if chosen == 3 else 0,
                                        "bw_logits": []}
    assert out["chosen"] == want
