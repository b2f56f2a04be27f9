"""Plot several training runs' returns in one figure.

    python -m benchmarks.curves runs/curve-mat runs/curve-mappo \
        --out docs/cheetah-6x1_mat_vs_mappo.png --title "cheetah-6x1, 2e6 steps" \
        --reference "paper: MAT at 1e7=9000"
"""

import argparse
from pathlib import Path

from mat_sdk.training.run_log import METRICS_NAME, plot_runs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("runs", nargs="+", type=Path, help="run directories (with metrics.csv)")
    parser.add_argument("--out", type=Path, required=True, help="PNG to write")
    parser.add_argument("--title")
    parser.add_argument(
        "--reference",
        action="append",
        default=[],
        metavar="LABEL=RETURN",
        help="a dashed line at RETURN, e.g. 'paper: MAT at 1e7=9000' (repeatable)",
    )
    args = parser.parse_args()
    runs = {run.name: run / METRICS_NAME for run in args.runs}
    references = {}
    for item in args.reference:
        label, _, value = item.rpartition("=")
        if not label:
            parser.error(f"--reference {item!r}: expected LABEL=RETURN")
        references[label] = float(value)
    print(plot_runs(runs, args.out, args.title, references))


if __name__ == "__main__":
    main()
