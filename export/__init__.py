"""Checkpoint -> ONNX bundle: `mat_export.export(checkpoint, out_dir)` or `mat export`."""

from mat_export.exporter import ExportError, export

__all__ = ["ExportError", "export"]
