"""Env stepping benchmark; same as `mat bench envs`. Run: python benchmarks/envs.py"""

from mat_sdk.bench.envs import main

if __name__ == "__main__":
    main()
