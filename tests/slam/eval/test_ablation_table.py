"""The ablation's Markdown table: figures that could not be measured are n/a, never 0/0 or a 0.00 recall."""
from __future__ import annotations

from slam.ablation import markdown_table


def _metrics(ate, loops=None, positives=None, before=0.0, after=0.0):
    m = {"ate_rmse": ate}
    if loops is not None:
        m["loops_true"], m["loops_false"] = loops
    if positives is not None:
        m["loop_detection"] = {
            "before_verification": {"num_positives": positives, "max_recall_at_full_precision": before},
            "after_verification": {"num_positives": positives, "max_recall_at_full_precision": after}}
    return m


def test_unmeasured_loops_and_recall_are_na():
    table = {"dam": {
        "kitchen": _metrics(0.0294, (36, 0), 40, 0.25, 0.9),  # measured: printed
        "no_revisit": _metrics(0.05, (0, 0), 0),  # no revisit in the ground truth: recall of nothing
        "no_gt": _metrics(None),  # no ground truth at all
        "none_found": _metrics(0.1, (0, 0), 12, 0.0, 0.0),  # revisits the detector missed: a real 0.00
    }}
    rows = markdown_table(table).splitlines()[-4:]  # the loop table: one row per sequence, one column (dam)
    assert rows == ["| kitchen | 36/0; 0.25 -> 0.90 |", "| no_revisit | 0/0; n/a |", "| no_gt | n/a; n/a |",
                    "| none_found | 0/0; 0.00 -> 0.00 |"]
