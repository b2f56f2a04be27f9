"""The learning tests' recipes over seeds; same as `mat bench seeds`.

Run: python benchmarks/seed_sweep.py --recipe game-mat --seeds 16
"""

import sys

from mat_sdk.cli import main

if __name__ == "__main__":
    main(["bench", "seeds", *sys.argv[1:]])
