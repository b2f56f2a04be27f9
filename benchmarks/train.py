"""Training throughput benchmark; same as `mat bench train`. Run: python benchmarks/train.py"""

from mat_sdk.bench.train import main

if __name__ == "__main__":
    main()
