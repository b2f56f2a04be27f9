"""Torch-free runtime for exported MAT bundles (numpy + onnxruntime only).

Not implemented yet: `mat export` bundles run today with onnxruntime directly (see README).
"""
