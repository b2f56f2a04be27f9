"""The transfer experiment's plan and report (the runs themselves: docs/TRANSFER.md)."""

import argparse
import csv

import pytest

from benchmarks import transfer


def _args(**changes):
    defaults = {"family": transfer.FAMILY, "train": [3, 4, 5], "targets": [8, 10], "pad": 12,
                "counts": list(range(2, 13)), "cells": None}  # fmt: skip
    return argparse.Namespace(**{**defaults, **changes})


def test_the_plan_has_every_cell_of_the_experiment():
    cells = transfer.train_cells(_args())
    assert set(cells) == {"multi", "multi-fraction", "multi-ends", "multi-near-ends",
                          "multi-end-flags", "multi-end-flags-window-4", "single", "padded",
                          "specialist-8", "specialist-10"}  # fmt: skip
    ids = [transfer.FAMILY.format(k) for k in (3, 4, 5)]
    id_free = {"position": None}  # named, or `mat train` would give a family "end-flags"
    assert cells["multi"] == (ids, id_free)
    assert cells["multi-ends"] == (ids, {"position": "ends"})
    assert cells["multi-end-flags"] == (ids, {"position": "end-flags"})
    assert cells["multi-end-flags-window-4"] == cells["multi-end-flags"]  # the model differs:
    assert transfer._model("multi-end-flags-window-4") == {"attention_window": 4}
    assert cells["single"] == ([transfer.FAMILY.format(4)], id_free)
    assert cells["padded"] == (ids, {"pad_agents": 12, "agent_id": True, **id_free})
    assert cells["specialist-10"] == ([transfer.FAMILY.format(10)], id_free)
    assert transfer.cells_counts("specialist-8", _args()) == [8]
    assert transfer.cells_counts("finetune-10/multi", _args()) == [10]
    assert transfer.cells_counts("padded", _args(pad=6)) == [2, 3, 4, 5, 6]


def test_a_subset_of_cells_runs_alone_and_a_misspelt_one_is_refused():
    cells = transfer.train_cells(_args(cells=["multi-ends", "specialist-8"]))
    assert set(cells) == {"multi-ends", "specialist-8"}
    with pytest.raises(SystemExit, match="unknown cells \\['specialist-9'\\]"):
        transfer.train_cells(_args(cells=["multi-ends", "specialist-9"]))


def test_the_report_compares_each_target_with_its_specialist(tmp_path):
    table = tmp_path / "results.csv"
    rows = [("random", 0, k, -10.0 * k) for k in (2, 8)]
    for seed, offset in ((0, 0.0), (1, 2.0)):
        rows += [("multi", seed, k, 10.0 + offset) for k in (2, 8)]
        rows += [("specialist-8", seed, 8, 20.0 + offset), ("finetune-8/multi", seed, 8, 25.0)]
    with table.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(transfer.FIELDS)
        writer.writerows([*row, 0.0] for row in rows)
    text = transfer.report(table, tmp_path / "plot.png", targets=[8])
    assert "| 8 | 11.0 ± 1.0 | -80.0 |" in text  # count, multi, random (seeds' spread)
    # with the random team at 0: (11 + 80) / (21 + 80); resampled seeds: 10 or 12 against
    # 20 or 22, from (10 + 80) / (22 + 80) to (12 + 80) / (20 + 80)
    assert "| 8 | multi | 2 | 11.0 ± 1.0 | 0.90 | 0.88 to 0.92 |" in text
    assert "| 8 | finetune-8/multi | 2 | 25.0 ± 0.0 | 1.04 | 1.03 to 1.05 |" in text
    assert (tmp_path / "plot.png").stat().st_size > 1000
