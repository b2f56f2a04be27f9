"""decode.onnx vs the step graph from Python; same as `mat bench decode`."""

from mat_export.bench import main

if __name__ == "__main__":
    main()
