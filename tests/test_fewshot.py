"""The few-shot experiment's table: one seed as before, several seeds with CIs over seeds."""

import csv
import subprocess
import sys
from pathlib import Path

import pytest

from benchmarks import fewshot

pytest.importorskip("rliable")

OLD_FIELDS = fewshot.FIELDS[:-1]  # tables written before seeds were repeated


def _write(path, fields, rows):
    with path.open("w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(fields)
        writer.writerows(rows)


def test_a_table_from_before_seeds_reads_as_seed_0(tmp_path):
    table = tmp_path / "fewshot.csv"
    _write(table, OLD_FIELDS, [["bthigh", "zero-shot", 0.0, 0, 445.0, 471.0],
                               ["bthigh", "finetune", 0.01, 100000, 1495.0, 1136.0]])  # fmt: skip
    text = fewshot.report(table, tmp_path / "fewshot.png", "mamujoco:HalfCheetah-6x1")
    assert "Seeds 0; each cell: mean ± std over episodes." in text
    assert "| bthigh | 445 ± 471 | 1495 ± 1136 |" in text


def test_several_seeds_give_the_mean_over_seeds_with_its_interval(tmp_path):
    table = tmp_path / "fewshot.csv"
    rows = []
    for seed, finetuned in enumerate([1000.0, 2000.0, 3000.0]):
        rows += [["fshin", "zero-shot", 0.0, 0, 300.0 + seed, 10.0, seed],
                 ["fshin", "finetune", 0.05, 500000, finetuned, 50.0, seed],
                 ["fshin", "scratch", 0.05, 500000, 900.0, 5.0, seed]]  # fmt: skip
    _write(table, fewshot.FIELDS, rows)
    text = fewshot.report(table, tmp_path / "fewshot.png", "mamujoco:HalfCheetah-6x1")
    assert "Seeds 0, 1, 2; each cell: mean over seeds [95 % CI]." in text
    line = next(line for line in text.splitlines() if line.startswith("| fshin"))
    zero, finetuned, scratch = (cell.strip() for cell in line.strip("|").split("|")[1:])
    assert zero == "300 ± 10"  # one policy: seed 0's evaluation, not a CI over copies
    mean, interval = finetuned.split(" ", 1)
    low, high = (float(v) for v in interval.strip("[]").split(","))
    assert mean == "2000" and 1000 <= low < 2000 < high <= 3000
    assert scratch == "900 [900, 900]"
    assert (tmp_path / "fewshot.png").stat().st_size > 0


def test_report_without_results_says_to_run_the_experiment_first(tmp_path):
    out = subprocess.run(
        [sys.executable, "-m", "benchmarks.fewshot", "zoo:halfcheetah-6x1-mat",
         "--out", str(tmp_path), "--report"],
        capture_output=True, text=True, cwd=Path(__file__).resolve().parents[1],
    )  # fmt: skip
    assert out.returncode == 2
    assert "no results in" in out.stderr and "run without --report" in out.stderr
