"""One control step: runtime vs official re-decode vs torch cached vs step graph (`mat bench
runtime`)."""

from mat_sdk.bench.runtime import main

if __name__ == "__main__":
    main()
